"""Settings: defaults, TOML fleet file, EQGW_ environment, validation errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from eqgw.config import ConfigError, Settings, load_settings

FLEET = """
database_url = "postgresql+asyncpg://postgres@127.0.0.1/test"
raw_archive = false

[writer]
batch_rows = 1000

[retention]
raw_days = 7

[[vehicles]]
id = "BUS-101"
name = "Bus 101"
depot = "North"

[[buses]]
name = "BUS-101/can0"
vehicle_id = "BUS-101"
interface = "socketcand"
channel = "can0"
options = { host = "10.0.0.5", port = 29536 }
equalizer_sas = [30, 31]
"""


@pytest.fixture(autouse=True)
def _clean_env(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    for key in list(os.environ):
        if key.startswith("EQGW_"):
            monkeypatch.delenv(key)


def test_defaults() -> None:
    s = load_settings()
    assert s.database_url == "sqlite:///eqgw.db"
    assert s.raw_archive is True
    assert s.vehicles == [] and s.buses == []
    assert s.retention.raw_days < s.retention.rollup_days
    assert s.writer.max_pending_rows > s.writer.batch_rows


def test_toml_file(tmp_path: Path) -> None:
    path = tmp_path / "fleet.toml"
    path.write_text(FLEET)
    s = load_settings(path)
    assert s.database_url.startswith("postgresql+asyncpg://")
    assert s.raw_archive is False
    assert s.writer.batch_rows == 1000
    assert s.retention.raw_days == 7
    assert s.vehicles[0].depot == "North"
    assert s.buses[0].options == {"host": "10.0.0.5", "port": 29536}
    assert s.buses[0].equalizer_sas == [30, 31]
    assert s.vehicle("BUS-101") is not None and s.vehicle("X") is None


def test_environment_over_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "fleet.toml"
    path.write_text(FLEET)
    monkeypatch.setenv("EQGW_CONFIG", str(path))
    monkeypatch.setenv("EQGW_DATABASE_URL", "sqlite:////tmp/other.db")
    monkeypatch.setenv("EQGW_WRITER__FLUSH_MS", "50")
    s = load_settings()
    assert s.database_url == "sqlite:////tmp/other.db"
    assert s.writer.flush_ms == 50
    assert s.writer.batch_rows == 1000  # from the file
    assert load_settings(path, database_url="sqlite:///x.db").database_url == "sqlite:///x.db"
    assert Settings().writer.flush_ms == 50  # plain Settings() reads EQGW_CONFIG too


def test_vehicles_from_environment_json(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("EQGW_VEHICLES", '[{"id": "A"}]')
    monkeypatch.setenv(
        "EQGW_BUSES",
        '[{"name": "A/can0", "vehicle_id": "A", "interface": "virtual", "channel": "x"}]',
    )
    s = load_settings()
    assert s.vehicles[0].display_name == "A"
    assert s.buses[0].equalizer_sas == [30]


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        (
            '[[buses]]\nname = "b"\nvehicle_id = "NOPE"\ninterface = "virtual"\nchannel = "c"\n',
            "refers to vehicle 'NOPE'",
        ),
        ('[[vehicles]]\nid = "A"\n[[vehicles]]\nid = "A"\n', "duplicate vehicle id(s): A"),
        ('database_url = "mysql://x/y"\n', "database_url"),
        ("unknown_key = 1\n", "unknown_key"),
        ("[writer]\nbatch_rows = 0\n", "writer.batch_rows"),
        (
            '[[vehicles]]\nid = "A"\n[[buses]]\nname = "b"\nvehicle_id = "A"\n'
            'interface = "virtual"\nchannel = "c"\nequalizer_sas = [300]\n',
            "buses.0.equalizer_sas",
        ),
        ("this is not toml", "cannot read"),
        # The checks the API and the CSV import share with the file (eqgw.fleet).
        (
            '[[vehicles]]\nid = "A"\n[[buses]]\nname = "b"\nvehicle_id = "A"\n'
            'interface = "socketcann"\nchannel = "c"\n',
            "buses.0.interface: Value error, 'socketcann' is not a python-can interface",
        ),
        (
            '[[vehicles]]\nid = "A"\n[[buses]]\nname = "b"\nvehicle_id = "A"\n'
            'interface = "virtual"\nchannel = "c"\noptions = { channel = "d" }\n',
            "channel is a field of the bus, not an option",
        ),
        ('[[vehicles]]\nid = "A/B"\n', "a vehicle id has no '/'"),
    ],
)
def test_invalid_configuration_is_a_clear_error(tmp_path: Path, toml: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(toml)
    with pytest.raises(ConfigError) as info:
        load_settings(path)
    assert message in str(info.value)


def test_missing_file() -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_settings("/nonexistent/fleet.toml")
