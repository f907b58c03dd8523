"""Profile validation: every wrong value is a load error naming the file, the key and what
was expected (issue 20's silent acceptances among them), never a default left in force."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from slipd.errors import ConfigError, SlipdError
from slipd.profile import PROFILE_DIR, load_profile

DEFAULT_TEXT = (PROFILE_DIR / "default.toml").read_text()


def _variant(tmp_path: Path, old: str, new: str, name: str = "variant.toml",
             text: str = DEFAULT_TEXT, dbc: str = "slipd.dbc") -> Path:
    assert old in text, old
    shutil.copy(PROFILE_DIR / dbc, tmp_path / dbc)
    path = tmp_path / name
    path.write_text(text.replace(old, new, 1))
    return path


@pytest.mark.parametrize("value", ["[nan, 0.0, 0.0]", "[inf, 0.0, 0.0]", "[1e300, 0.0, 0.0]",
                                   "[true, 0.0, 0.0]", "[0.25, 0.05]", '["0.25", 0, 0]'])
def test_imu_position_must_be_three_finite_metres(tmp_path, value):
    path = _variant(tmp_path, "imu_position = [0.25, 0.05, -0.25]", f"imu_position = {value}")
    with pytest.raises(ConfigError, match=r"\[vehicle\] imu_position .*three finite numbers"):
        load_profile(path)


def test_a_timeout_of_1e300_seconds_is_refused(tmp_path):
    path = _variant(tmp_path, "rate_hz = 100.0\ntimeout = 0.03", "rate_hz = 100.0\n"
                    "timeout = 1e300")
    with pytest.raises(ConfigError, match=r"\[messages.IMU_ACCEL\] timeout = 1e\+300; "
                                          "expected at most 60"):
        load_profile(path)
    path = _variant(tmp_path, 'unit = "m/s^2" }', 'unit = "m/s^2", timeout = 1e300 }')
    with pytest.raises(ConfigError, match=r"\[channels.ax\] timeout"):
        load_profile(path)


@pytest.mark.parametrize("value", ["true", "[true] ", "[1, 2]"])
def test_data_ids_must_be_sixteen_bytes_of_an_autosar_message(tmp_path, value):
    path = _variant(tmp_path, 'e2e = "slipd_crc8"\ncrc_signal = "IMU_ACCEL_CRC"',
                    f'e2e = "autosar_crc8"\ndata_ids = {value}\ncrc_signal = "IMU_ACCEL_CRC"')
    with pytest.raises(ConfigError, match=r"\[messages.IMU_ACCEL\] data_ids"):
        load_profile(path)
    path = _variant(tmp_path, 'e2e = "slipd_crc8"\ncrc_signal = "IMU_ACCEL_CRC"',
                    f'e2e = "slipd_crc8"\ndata_ids = {value}\ncrc_signal = "IMU_ACCEL_CRC"')
    with pytest.raises(ConfigError, match=r"\[messages.IMU_ACCEL\] data_ids"):
        load_profile(path)


def test_a_dbc_scale_of_zero_is_refused(tmp_path):
    shutil.copy(PROFILE_DIR / "slipd.dbc", tmp_path / "slipd.dbc")
    dbc = tmp_path / "slipd.dbc"
    text = dbc.read_text()
    line = next(x for x in text.splitlines() if " SG_ ACCEL_X " in x)
    dbc.write_text(text.replace(line, re.sub(r"\(([^,]+),", "(0,", line, count=1)))
    (tmp_path / "p.toml").write_text(DEFAULT_TEXT)
    with pytest.raises(SlipdError, match="ACCEL_X has scale 0"):
        load_profile(tmp_path / "p.toml")


def test_slipds_own_output_message_is_not_an_input(tmp_path):
    path = _variant(tmp_path, "[messages.IMU_ACCEL]", '[messages.SLIPD_STATE]\ne2e = "none"\n'
                    "rate_hz = 100.0\n\n[messages.IMU_ACCEL]")
    with pytest.raises(ConfigError, match=r"\[messages.SLIPD_STATE\] is slipd's own output"):
        load_profile(path)


def test_an_input_on_an_output_id_is_refused(tmp_path):
    path = _variant(tmp_path, "[channels]", "[outputs]\nstate_id = 0x100\n\n[channels]")
    with pytest.raises(ConfigError, match="IMU_ACCEL has frame ID 0x100 .* SLIPD_STATE"):
        load_profile(path)


def test_a_non_utf8_profile_is_a_config_error(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes(DEFAULT_TEXT.replace("BMW 320i", "BMW 320i \u00e9").encode("latin-1"))
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_profile(path)


def test_a_channel_without_unit_is_a_load_error_naming_the_dbc_unit(tmp_path):
    path = _variant(tmp_path, 'signal = "WHEEL_SPEED_FL", unit = "km/h" }',
                    'signal = "WHEEL_SPEED_FL" }')
    with pytest.raises(ConfigError, match=r"\[channels\] wheel_speed_fl: unit is missing; the "
                                          r"DBC gives WHEEL_SPEEDS.WHEEL_SPEED_FL in 'km/h'"):
        load_profile(path)


def test_a_unit_against_the_dbc_unit_is_a_load_error(tmp_path):
    path = _variant(tmp_path, 'signal = "WHEEL_SPEED_FL", unit = "km/h" }',
                    'signal = "WHEEL_SPEED_FL", unit = "m/s" }')
    with pytest.raises(ConfigError, match="unit = 'm/s', but the DBC gives"):
        load_profile(path)


def test_a_unit_of_another_dimension_is_refused(tmp_path):
    path = _variant(tmp_path, 'signal = "YAW_RATE", unit = "deg/s" }',
                    'signal = "YAW_RATE", unit = "deg" }')
    with pytest.raises(ConfigError, match="'deg' is a unit of angle, but yaw_rate is a "
                                          "angular rate"):
        load_profile(path)


def test_qualifier_needs_its_valid_values(tmp_path):
    path = _variant(tmp_path, 'signal = "YAW_RATE", unit = "deg/s" }',
                    'signal = "YAW_RATE", unit = "deg/s", valid_signal = "ROLL_RATE" }')
    with pytest.raises(ConfigError, match="valid_values is missing"):
        load_profile(path)


def test_sign_signal_must_exist_and_be_one_bit(tmp_path):
    path = _variant(tmp_path, 'signal = "YAW_RATE", unit = "deg/s" }',
                    'signal = "YAW_RATE", unit = "deg/s", sign_signal = "NOPE" }')
    with pytest.raises(SlipdError, match="has no sign_signal 'NOPE'"):
        load_profile(path)
    path = _variant(tmp_path, 'signal = "YAW_RATE", unit = "deg/s" }',
                    'signal = "YAW_RATE", unit = "deg/s", sign_signal = "ROLL_RATE" }')
    with pytest.raises(SlipdError, match="a sign is 1 bit"):
        load_profile(path)


def test_shipped_profiles_load():
    for path in sorted(PROFILE_DIR.glob("*.toml")):
        assert load_profile(path.stem).name == path.stem


def test_import_reads_the_shipped_toyota_dbc(tmp_path):
    """`slipd import` loaded the production DBC strictly and crashed on it; the codec's
    non-strict loader is shared now."""
    from slipd.cli import main

    csv = tmp_path / "drive.csv"
    csv.write_text("t,ax,ay,yaw\n" + "".join(f"{k * 0.0125:.4f},0.5,-1.0,3.0\n"
                                              for k in range(40)))
    out = tmp_path / "drive.log"
    assert main(["import", str(csv), "--profile", "toyota_prius", "--map",
                 "ax=ax:m/s^2,ay=ay:m/s^2,yaw=yaw_rate:deg/s", "--out", str(out)]) == 0
    assert out.read_text().count("\n") == 40


def test_accelerometer_frame_is_declared_per_imu_message(tmp_path):
    """frame = body|level on the message carrying the accelerometers (issue 17 item 1):
    default body; anything else, or on a message without accelerometers, is a load error."""
    from slipd.profile import PROFILE_DIR

    text = (PROFILE_DIR / "default.toml").read_text()
    assert load_profile("default").accel_frame == "body"

    def variant(old: str, new: str) -> Path:
        path = tmp_path / "p.toml"
        path.write_text(text.replace(old, new).replace('dbc = "slipd.dbc"',
                                                       f'dbc = "{PROFILE_DIR / "slipd.dbc"}"'))
        return path

    assert load_profile(variant('frame = "body"', 'frame = "level"')).accel_frame == "level"
    assert load_profile(variant('frame = "body"\n', '')).accel_frame == "body"
    with pytest.raises(ConfigError, match="frame = 'tilted'; expected one of"):
        load_profile(variant('frame = "body"', 'frame = "tilted"'))
    with pytest.raises(ConfigError, match=r"IMU_RATE\] frame = 'level': the message carries no"):
        load_profile(variant('counter_signal = "IMU_RATE_Counter"',
                             'counter_signal = "IMU_RATE_Counter"\nframe = "level"'))
