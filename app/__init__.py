"""eqgw: fleet gateway for Vanner VANN-Guard battery equalizers."""


def version() -> str:
    """The installed distribution's version (a checkout that was never installed: unknown)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("eqgw")
    except PackageNotFoundError:
        return "0+unknown"
