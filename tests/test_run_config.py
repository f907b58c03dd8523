"""`slipd run` configuration: every bad value is one clear line naming the key (never a
traceback), strings are never cast to booleans, and the shipped example config works."""

from __future__ import annotations

import argparse
import socket
from pathlib import Path

import pytest

from slipd.cli import main
from slipd.commands.run import add_arguments, daemon_config, read_config

EXAMPLE = Path(__file__).resolve().parent.parent / "systemd" / "slipd.toml"


def _run(capsys, *argv: str) -> str:
    assert main(["run", *argv]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def _config(tmp_path, text: str) -> str:
    path = tmp_path / "slipd.toml"
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize(("line", "expected"), [
    ('sched_fifo = "high"', "sched_fifo = 'high': expected an integer 0..99"),
    ('cpu = "x"', "cpu = 'x': expected an integer"),
    ('mlockall = "false"', "mlockall = 'false': expected true or false"),
    ("timer_slack_ns = -5", "timer_slack_ns = -5: expected an integer 1..10000000"),
    ("spin_us = 5000", "spin_us = 5000: expected an integer 0..4999"),
    ("prometheus = true", "prometheus = True: expected"),
    ("recorder_keep = -1", "recorder_keep = -1"),
    ("silence_warning_s = nan", "silence_warning_s = nan"),
    ("stats_socket = 7", "stats_socket = 7: expected a non-empty string"),
    ("gc_freeze = 1", "gc_freeze = 1: expected true or false"),
    ("colour = 3", "unknown key(s) ['colour']"),
])
def test_bad_config_values_name_file_key_and_expectation(tmp_path, capsys, line, expected):
    path = _config(tmp_path, line + "\n")
    err = _run(capsys, "--config", path, "--interface", "virtual", "--channel", "cfg")
    assert f"{path}: " in err and expected in err


def test_a_non_utf8_config_is_a_clear_error(tmp_path, capsys):
    path = tmp_path / "slipd.toml"
    path.write_bytes(b'channel = "can0\xff"\n')
    assert "cannot read config" in _run(capsys, "--config", str(path))


def test_mlockall_false_does_not_lock_memory(tmp_path):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--config", _config(tmp_path, "mlockall = false\n"),
                              "--interface", "virtual"])
    assert daemon_config(args).realtime.mlockall is False


@pytest.mark.parametrize(("argv", "expected"), [
    (["--prometheus", "127.0.0.1:abc"], "port 'abc' is not a number"),
    (["--prometheus", "0.0.0.0:9464"], "--prometheus-public"),
    (["--stats-socket", "/nonexistent/dir/sock"], "directory /nonexistent/dir does not exist"),
    (["--duration", "nan"], "--duration nan"),
    (["--spin-us", "-3"], "option --spin-us: spin_us = -3"),
    (["--timer-slack-ns", "0"], "timer_slack_ns = 0: expected an integer 1.."),
])
def test_bad_options_are_clear_errors(tmp_path, capsys, argv, expected):
    err = _run(capsys, "--config", _config(tmp_path, ""), "--interface", "virtual",
               "--channel", "cfg", *argv)
    assert expected in err


def test_a_port_in_use_is_refused_before_start(tmp_path, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        err = _run(capsys, "--config", _config(tmp_path, ""), "--interface", "virtual",
                   "--channel", "cfg", "--prometheus", f"127.0.0.1:{taken.getsockname()[1]}")
    assert "cannot listen there: Address already in use" in err


def test_an_unknown_interface_lists_the_known_ones(tmp_path, capsys):
    err = _run(capsys, "--config", _config(tmp_path, ""), "--interface", "nosuch")
    assert "--interface 'nosuch'" in err and "socketcan" in err and "virtual" in err


def test_socketcan_without_can_in_the_kernel_says_so(tmp_path, capsys):
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
        pytest.skip("this kernel has CAN sockets (the VM tests cover socketcan)")
    except OSError:
        pass
    err = _run(capsys, "--config", _config(tmp_path, ""), "--interface", "socketcan",
               "--channel", "can0")
    assert "this kernel has no CAN sockets" in err and "can_raw" in err


def test_the_example_config_is_valid_and_means_what_it_says():
    """The README told users to copy a vehicle profile to /etc/slipd/slipd.toml, which the
    daemon refused; systemd/slipd.toml is the example that works."""
    settings = read_config(EXAMPLE)
    assert settings["interface"] == "socketcan" and settings["channel"] == "can0"
    assert settings["prometheus"] == "127.0.0.1:9464"
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    config = daemon_config(parser.parse_args(["--config", str(EXAMPLE)]))
    assert config.profile.name == "default"
    assert config.realtime.sched_fifo == settings["sched_fifo"]
