"""The shipped DBC as other CAN tools see it: true data ranges, named "not available" values,
and names unique enough for an ARXML export (canmatrix) that loads."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import cantools
import pytest
from cantools.database.can import Database

from eqgw.protocol import dbc

DBC_FILE = Path(dbc.__file__).with_name("vanner_equalizer.dbc")
# Messages whose 16- and 8-bit values follow J1939's data / error / not-available ranges.
J1939_VALUED = {"voltages": "not_available", "battery_states": "not_available"}
TO_EQUALIZER = {"parameters": "not_requested"}


def _file_db() -> Database:
    """The file as any cantools user loads it (no renaming of ours)."""
    db = cantools.database.load_file(str(DBC_FILE), strict=True)
    assert isinstance(db, Database)
    return db


def _numeric(db: Database, message: str) -> list[cantools.database.can.Signal]:
    return [
        s
        for s in db.get_message_by_name(message).signals
        if s.length in (8, 16) and not s.is_multiplexer and s.name != "calibration"
    ]


@pytest.mark.parametrize("message", [*J1939_VALUED, *TO_EQUALIZER])
def test_declared_ranges_end_at_the_last_data_value(message: str) -> None:
    """A tool must not show raw 0xFFFF as an in-range reading (v12 was [0|327.675])."""
    for sig in _numeric(_file_db(), message):
        last_data = 0xFAFF if sig.length == 16 else 0xFA
        top = last_data * sig.scale + sig.offset
        assert sig.maximum is not None and sig.maximum <= top + 1e-9, sig.name
        assert sig.minimum is not None and sig.minimum >= sig.offset - 1e-9, sig.name
    voltages = _file_db().get_message_by_name("voltages")
    assert voltages.get_signal_by_name("v12").maximum == pytest.approx(321.275)
    assert voltages.get_signal_by_name("v24").maximum == pytest.approx(321.275)


@pytest.mark.parametrize("message", [*J1939_VALUED, *TO_EQUALIZER])
def test_all_ones_is_named_not_a_number(message: str) -> None:
    name = {**J1939_VALUED, **TO_EQUALIZER}[message]
    db = _file_db()
    for sig in _numeric(db, message):
        assert sig.choices is not None, sig.name
        all_ones = (1 << sig.length) - 1
        assert str(sig.choices[all_ones]) == name, sig.name
        if message in J1939_VALUED:
            assert str(sig.choices[0xFE00 if sig.length == 16 else 0xFE]) == "error"


def test_a_missing_voltage_reads_not_available_in_cantools() -> None:
    voltages = _file_db().get_message_by_name("voltages")
    decoded = voltages.decode(bytes.fromhex("FFFFB013BA7CC87D"))
    assert str(decoded["v12"]) == "not_available" and decoded["v24"] == 25.2


def test_signal_names_are_unique_and_records_keep_the_dictionary_names() -> None:
    db = _file_db()
    names = Counter(s.name for m in db.messages for s in m.signals)
    assert [n for n, c in names.items() if c > 1] == []
    assert not set(names) & {m.name for m in db.messages}
    # The package's database maps them back: the record fields of SPEC-NOTES.
    assert [s.name for s in dbc.message("heartbeat").signals] == ["heartbeat"]
    assert dbc.message("parameters").get_signal_by_name("soc_12v").multiplexer_ids == [7]
    assert dbc.field_name("parameters", "param_index") == "index"
    assert dbc.field_name("voltages", "v12") == "v12"


def _short_name_paths(path: Path) -> Counter[str]:
    from lxml import etree

    paths: Counter[str] = Counter()
    for el in etree.parse(str(path)).iter():
        if el.find("{*}SHORT-NAME") is None:
            continue
        parts = []
        node = el
        while node is not None:
            short = node.find("{*}SHORT-NAME")
            if short is not None:
                parts.append(short.text)
            node = node.getparent()
        paths["/".join(reversed(parts))] += 1
    return paths


def test_canmatrix_arxml_export_loads(tmp_path: Path) -> None:
    canmatrix_formats = pytest.importorskip("canmatrix.formats")
    # Through our own file objects: canmatrix's path functions leave their files open.
    with DBC_FILE.open("rb") as f:
        matrix = canmatrix_formats.load_flat(f, "dbc")
    signals = sum(len(f.signals) for f in matrix.frames)
    assert (len(matrix.frames), signals) == (13, 92)
    for version in ("3.2.3", "4.1.0"):
        out = tmp_path / f"eq-{version}.arxml"
        with out.open("wb") as f:
            canmatrix_formats.dump({"": matrix}, f, "arxml", arVersion=version)
        # The cause of "multiple elements with path": two elements under one path.
        assert [p for p, n in _short_name_paths(out).items() if n > 1] == [], version
    with (tmp_path / "eq-4.1.0.arxml").open("rb") as f:
        back = canmatrix_formats.load_flat(f, "arxml")
    assert len(back.frames) == 13
    assert sorted(s.name for f in back.frames for s in f.signals) == sorted(
        s.name for f in matrix.frames for s in f.signals
    )
    # cantools reads canmatrix's AR3 export (not strict: that export drops multiplexing, so
    # the multiplexed signals overlap; its AR4 export lacks a BASE-TYPE-ENCODING cantools wants).
    arxml = cantools.database.load_file(str(tmp_path / "eq-3.2.3.arxml"), strict=False)
    assert len(arxml.messages) == 13
    assert sum(len(m.signals) for m in arxml.messages) == 92
