"""eqgw: fleet gateway for Vanner VANN-Guard battery equalizers.

The folder `app/` is the package `eqgw` (pyproject's `package-dir`). Imported under its folder
name (`import app`, from a checkout's root) it would load a second copy of every module beside
`eqgw`'s, with its own settings, metrics and caches; that import fails here instead.

The data path is layered: `protocol` (pure decode/encode) -> `bus` (python-can I/O) ->
`ingest` (live state, faults, batched writes) -> `store` (the tables, SQL of the time series).
The features a user calls are domains: `security`, `commands`, `alerts`, `notify`, `fleet`,
`forward`; `api` composes them into the HTTP service; `cluster` shares buses between gateways;
`sim` is the simulated fleet.
"""

if __name__ != "eqgw":  # pragma: no cover - the message is the behaviour
    raise ImportError(
        f"the package folder app/ is imported as '{__name__}': import it as 'eqgw' "
        "(pip install -e . makes 'eqgw' importable from a checkout)"
    )

from eqgw.bus import mf4 as _mf4

_mf4.defer()  # asammdf (the mf4 extra) is imported when an MF4 log is read or written, not before


def version() -> str:
    """The installed distribution's version (a checkout that was never installed: unknown)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("eqgw")
    except PackageNotFoundError:
        return "0+unknown"
