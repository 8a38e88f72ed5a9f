"""Reading and validating user CSV records and device TOML files (accel_jax._data)."""

import numpy as np
import pytest

import accel_jax as aj
from accel_jax._data import (
    COLUMNS,
    MIN_SAMPLES,
    DataError,
    NoiseData,
    StepData,
    VibrationData,
    infer_kind,
    parse_csv,
    parse_params_toml,
    read_csv,
    read_params_toml,
    write_csv,
)


def _step_text(n=300, dt=1e-5, header="t,u_test,u_out"):
    t = np.arange(n) * dt
    u = np.where(t > n * dt / 2, 1.0, 0.0)
    y = 0.9 * u + 1e-3 * np.sin(t * 1e3)
    rows = "\n".join(
        f"{float(a)!r},{float(b)!r},{float(c)!r}" for a, b, c in zip(t, u, y, strict=True)
    )
    return header + "\n" + rows + "\n", (t, u, y)


def _vibration_text(rows=10):
    lines = ["a_in,vib_amp,vib_freq,vib_rms,a_out"]
    for i in range(rows):
        lines.append(f"{i - 5},{0.5 * i},{10 * i + 5},0,{i - 5 + 1e-4 * i}")
    return "\n".join(lines) + "\n"


def _noise_text(n=300):
    t = np.arange(n) * 1e-3
    a = 1e-5 * np.cos(t)
    return (
        "a_out,t\n"
        + "\n".join(f"{float(y)!r},{float(x)!r}" for x, y in zip(t, a, strict=True))
        + "\n"
    )


def test_step_parsed_exactly():
    text, (t, u, y) = _step_text()
    data = parse_csv(text)
    assert isinstance(data, StepData) and data.kind == "step"
    np.testing.assert_array_equal(data.t, t)
    np.testing.assert_array_equal(data.u_test, u)
    np.testing.assert_array_equal(data.u_out, y)
    assert data.sample_period == pytest.approx(1e-5, rel=1e-12)


def test_kinds_inferred_from_columns_in_any_order():
    assert isinstance(parse_csv(_vibration_text()), VibrationData)
    noise = parse_csv(_noise_text())
    assert isinstance(noise, NoiseData)
    np.testing.assert_allclose(noise.a_out[:3], 1e-5 * np.cos(np.arange(3) * 1e-3), rtol=1e-15)
    for kind, columns in COLUMNS.items():
        assert infer_kind(list(reversed(columns))) == kind


def test_forced_kind_must_match_columns():
    text, _ = _step_text()
    assert parse_csv(text, kind="step").kind == "step"
    with pytest.raises(DataError, match="'noise' record"):
        parse_csv(text, kind="noise")
    with pytest.raises(DataError, match="unknown kind"):
        parse_csv(text, kind="shaker")


def test_csv_round_trip(tmp_path):
    _, (t, u, y) = _step_text()
    path = write_csv(tmp_path / "r.csv", StepData(t, u, y))
    back = read_csv(path)
    np.testing.assert_array_equal(back.u_out, y)  # repr() keeps every float64 bit
    assert not list(tmp_path.glob(".*tmp"))


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty"),
        ("\n\n  \n", "empty"),
        ("t,u_test,u_out\n", "only a header"),
        ("t,u_out\n0,1\n", r"closest is 'step'.*missing column\(s\) \['u_test'\]"),
        ("t,u_test\n0,1\n", "missing column"),
        ("t,u_test,u_out,temp\n0,1,2,3\n", "unknown column"),
        ("t,t,u_out\n0,1,2\n", "duplicated column"),
        ("t,u_test,u_out\n0,1\n", "row 2 has 2 field"),
        ("t,u_test,u_out\n0,1,abc\n", "'abc', not a number"),
    ],
)
def test_bad_csv_structure(text, message):
    with pytest.raises(DataError, match=message):
        parse_csv(text, path="x.csv")


def test_fast_reader_agrees_with_the_field_by_field_one():
    """NumPy's C reader (`_fast_values`) reads plain numeric rows; every other form falls
    back to `float` field by field, so a file reads the same either way."""
    from accel_jax._data import _checked_values, _fast_values

    rows = ["0, 1.5e-3 ", "+1,.5", "2.,-Infinity", "3,nan", "4,1E+2", "5,-0.0"]
    fast = _fast_values(rows, 2)
    slow = _checked_values([r.split(",") for r in rows], ["t", "a_out"], "x.csv")
    np.testing.assert_array_equal(fast, slow)
    # forms NumPy refuses and Python's float reads, quoted fields, inline '#': the slow path
    for odd in (['0,"1.5"', "1,2"], ["0,1_0", "1,2"], ["0,1 # c", "1,2"], ["0,1,2", "1,2"]):
        assert _fast_values(odd, 2) is None
    text = "t,a_out\n" + "\n".join(f'{i * 0.01!r},"{i * 1e-3!r}"' for i in range(300))
    np.testing.assert_array_equal(parse_csv(text).a_out, np.arange(300) * 1e-3)


def _modified(column, index, value):
    text, (t, u, y) = _step_text()
    arrays = {"t": t.copy(), "u_test": u.copy(), "u_out": y.copy()}
    arrays[column][index] = value
    rows = zip(arrays["t"], arrays["u_test"], arrays["u_out"], strict=True)
    return "t,u_test,u_out\n" + "\n".join(
        f"{float(a)!r},{float(b)!r},{float(c)!r}" for a, b, c in rows
    )


@pytest.mark.parametrize(
    "column, index, value, message",
    [
        ("u_out", 7, np.nan, r"'u_out' row 9 is nan V"),
        ("u_test", 3, np.inf, r"'u_test' row 5 is inf V"),
        ("t", 10, 5e-5, r"increase strictly; row 12"),
        ("t", 10, 10.2e-5, "sampling must be uniform"),
        # A finite value no measurement reaches: refused, not an overflow in the fits.
        ("u_out", 4, 1e300, r"'u_out' row 6 is 1e300 V; no value may exceed 1e30 in size"),
        ("u_test", 4, -2e31, r"'u_test' row 6 is -2e31 V; no value may exceed"),
    ],
)
def test_bad_csv_values(column, index, value, message):
    with pytest.raises(DataError, match=message):
        parse_csv(_modified(column, index, value), path="x.csv")


def test_too_few_samples_and_rows():
    text, _ = _step_text(n=MIN_SAMPLES["step"] - 1)
    with pytest.raises(DataError, match=f"at least {MIN_SAMPLES['step']} samples, got 199"):
        parse_csv(text)
    with pytest.raises(DataError, match="at least 8 rows, got 5"):
        parse_csv(_vibration_text(rows=5))


def test_vibration_amplitude_must_be_non_negative_and_step_must_step():
    text = _vibration_text().replace("\n2,3.5,", "\n2,-3.5,")
    with pytest.raises(DataError, match="'vib_amp' row 9 is -3.5 g"):
        parse_csv(text)
    text, _ = _step_text()
    lines = text.splitlines()
    flat = [lines[0]] + [",".join([r.split(",")[0], "0.5", r.split(",")[2]]) for r in lines[1:]]
    with pytest.raises(DataError, match="u_test is constant"):
        parse_csv("\n".join(flat))


def test_missing_file_is_a_data_error(tmp_path):
    with pytest.raises(DataError, match="no such file"):
        read_csv(tmp_path / "absent.csv")
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(DataError, match="not a text"):
        read_csv(tmp_path / "bin.csv")


def test_data_error_is_a_value_error():
    assert issubclass(DataError, ValueError)


# --- device files ------------------------------------------------------------------------


def test_params_toml_values_and_uncertainty(tmp_path):
    path = tmp_path / "dev.toml"
    path.write_text(
        "damping = 3.0e-5\n"
        "stiffness = { value = 2.9e-4, uncertainty = 0.1 }\n"
        "torquer_gain = { uncertainty = 0.0 }\n"
    )
    device = read_params_toml(path)
    assert float(device.params.damping) == 3.0e-5
    assert float(device.params.stiffness) == 2.9e-4
    assert float(device.params.moment_of_inertia) == aj.REFERENCE_VALUES["moment_of_inertia"]
    assert device.uncertainty == {"moment_of_inertia": 0.05, "damping": 0.05, "stiffness": 0.1}


@pytest.mark.parametrize(
    "text, message",
    [
        ("dampnig = 1e-5\n", r"unknown key\(s\) \['dampnig'\]"),
        ("damping = { value = 1e-5, sigma = 0.1 }\n", r"unknown key\(s\) \['sigma'\]"),
        ('damping = "big"\n', "damping = 'big' is not a number"),
        ("damping = nan\n", "is not finite"),
        ("damping = { uncertainty = 1.5 }\n", r"must lie in \[0, 1.0\]"),
        ("pendulum_mass = -1.0\n", "must be positive, got"),
        ("damping = = 1\n", "not valid TOML"),
    ],
)
def test_bad_params_toml(text, message):
    with pytest.raises(DataError, match=message):
        parse_params_toml(text, path="dev.toml")


def test_error_messages_quote_numbers_as_written():
    """A value quoted back to the user reads 0.3, not 0.30000000000000004 (10 significant
    figures: two nearby time stamps stay distinct)."""
    from accel_jax._data import DataError, parse_csv
    from accel_jax._format import number, percent, precise, seconds

    assert precise(0.1 + 0.2) == "0.3" and precise(1.2999999999999998) == "1.3"
    assert precise(1.000000001) != precise(1.000000002)
    assert number(None) == "—" and number(float("nan")) == "—" and number(2.5e-5) == "2.5e-5"
    assert seconds(2.5e-5) == "25 µs" and seconds(0.0012) == "1.2 ms"
    assert percent(0.0131) == "+1.31 %"
    t = np.arange(300) * 0.1  # t[3] = 0.30000000000000004
    t[4] = 0.299
    u = np.where(np.arange(300) >= 100, 1.0, 0.0)
    text = "t,u_test,u_out\n" + "\n".join(
        f"{a!r},{b!r},{b!r}" for a, b in zip(t.tolist(), u.tolist(), strict=True)
    )
    with pytest.raises(DataError) as error:
        parse_csv(text)
    message = str(error.value)
    assert "t = 0.299 s after t = 0.3 s" in message and "0000000" not in message


def test_a_csv_with_a_byte_order_mark_is_read(tmp_path):
    # Spreadsheet programs save "CSV UTF-8" with a BOM: it was refused ("unexpected
    # ['\ufefft']"); read as the same file without it.
    text, _ = _step_text()
    plain, marked = tmp_path / "plain.csv", tmp_path / "bom.csv"
    plain.write_text(text, encoding="utf-8")
    marked.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    a, b = aj.read_csv(plain), aj.read_csv(marked)
    assert np.array_equal(a.u_out, b.u_out) and np.array_equal(a.t, b.t)
