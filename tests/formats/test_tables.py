"""The CSV tables' columns, parsed at once by numpy, give exactly what the row-by-row parse
gives (Python's int() and float()), and a bad value is named by its own row's line."""

import numpy as np
import pytest

from pancam_graph.errors import InputError
from pancam_graph.formats.tables import CsvTable

# texts Python's float() and int() take beyond plain digits: numpy must take them alike
ODD = [" 5", "5 ", "\t7", "1_0", "00012", "-0", "+1", "１", "٣"]


def _table(tmp_path, rows: list[tuple[str, str, str]]) -> CsvTable:
    path = tmp_path / "t.csv"
    path.write_text("stop,track,u\n" + "".join(",".join(r) + "\n" for r in rows), encoding="utf-8")
    return CsvTable(path, ["stop", "track", "u"])


def test_columns_parsed_at_once_equal_the_row_by_row_parse(tmp_path):
    rng = np.random.default_rng(0)
    floats = [repr(float(x)) for x in rng.uniform(-100, 2000, 200)] + ODD + ["1.", ".5", "1e2"]
    rows = [(str(k % 7), ODD[k % len(ODD)] if k % 5 == 0 else str(k), floats[k]) for k in range(len(floats))]
    table = _table(tmp_path, rows)
    table.check_widths()
    u = table.numbers("u")
    assert u.tolist() == [float(r[2]) for r in rows]
    assert np.signbit(u[floats.index("-0")])  # -0.0 kept as float() keeps it
    assert table.stops(7).tolist() == [int(r[0]) for r in rows]
    assert table.tracks().tolist() == [int(r[1]) for r in rows]
    assert table.pixels("u", 1024).tolist() == u.tolist()


@pytest.mark.parametrize("bad_stop, bad_track, bad_u, message", [
    ("3", "2", "nan", "line 3: column 'u' is not finite"),
    ("3", "2", "1e400", "line 3: column 'u' is not finite"),
    ("3", "2", "4000", "line 3: column 'u' = 4000 px lies more than an image size (1024 px) outside the image"),
    ("9", "2", "1", "line 3: stop 9 is not one of stereo.csv's stops 0..6"),
    ("3", "-1", "1", "line 3: track -1 outside 0..2^63-1"),
    ("3", "9" * 25, "1", f"line 3: track {'9' * 25} outside 0..2^63-1"),
    ("3", "2.5", "1", "line 3: column 'track': expected an integer, got '2.5'"),
])
def test_the_first_bad_row_of_a_column_is_named(tmp_path, bad_stop, bad_track, bad_u, message):
    rows = [("0", "1", "10.0"), (bad_stop, bad_track, bad_u), ("1", "5", "nan")]  # line 4 is bad too
    table = _table(tmp_path, rows)
    with pytest.raises(InputError) as refused:
        table.check_widths()
        table.stops(7), table.tracks(), table.pixels("u", 1024)
    assert str(refused.value) == f"{table.path}: {message}"
