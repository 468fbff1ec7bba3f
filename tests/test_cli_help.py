"""The CLI's help is true and complete: every option of every subcommand has a help text naming
its default, the top-level help says which subcommands take --env-config, and Warp's
no-CUDA-driver line stays off stderr on machines without a driver."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

import pytest

import tg_gpudrive
from tg_gpudrive.cli import build_parser


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    raise AssertionError("no subcommands")


def _parsers() -> dict[str, argparse.ArgumentParser]:
    top = build_parser()
    return {"tg-gpudrive": top, **_subparsers(top)}


def test_every_option_has_help_with_its_default():
    missing = []
    for name, parser in _parsers().items():
        formatter = parser._get_formatter()
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)) or not action.option_strings:
                continue
            text = formatter._expand_help(action) if action.help else ""
            flag = f"{name} {action.option_strings[-1]}"
            if not text.strip():
                missing.append(f"{flag}: no help")
            elif not action.required and "default" not in text and "required" not in text:
                missing.append(f"{flag}: no default in {text!r}")
    assert not missing, "\n".join(missing)


def test_named_flags_show_their_defaults():
    p = _parsers()
    simulate = p["simulate"].format_help()
    for text in ("worlds simulated in parallel, one scene each (default: 16)", "(default: 0)",
                 "(default: expert)", "collision_mode"):
        assert text in " ".join(simulate.split()), text
    assert "frames per second of a .gif / .mp4 (default: 10.0)" in " ".join(p["render"].format_help().split())
    assert "the store directory to write (required)" in " ".join(p["convert"].format_help().split())
    report = " ".join(p["report"].format_help().split())
    for text in ("per run (default: 4)", "(default: 0 1)", "(default: 5)"):
        assert text in report, text
    assert "default: warnings only" in " ".join(p["tg-gpudrive"].format_help().split())


def test_top_level_help_names_the_subcommands_that_take_env_config():
    parsers = _parsers()
    top = " ".join(parsers["tg-gpudrive"].format_help().split())
    assert "Every subcommand takes" not in top
    assert "simulate, benchmark, evaluate and render take `--env-config`" in top
    assert "report and convert take neither" in top
    for name in ("simulate", "benchmark", "evaluate", "render"):
        assert "--env-config" in parsers[name].format_help(), name
    for name in ("train", "train-world-model", "report", "convert"):
        assert "--env-config" not in parsers[name].format_help(), name


def test_simulate_help_from_the_command_line():
    out = subprocess.run([sys.executable, "-m", "tg_gpudrive.cli", "simulate", "--help"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    text = " ".join(out.stdout.split())
    assert "(default: 16)" in text and "(default: procedural:all)" in text
    assert tg_gpudrive.NO_DRIVER_WARNING not in out.stderr


@pytest.mark.skipif(tg_gpudrive._cuda_driver_loadable(), reason="a CUDA driver loads here: Warp prints no such line")
def test_no_cuda_driver_warning_on_a_cpu_machine():
    code = "import tg_gpudrive, warp; warp.init(); print(warp.is_cuda_available())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr
    assert tg_gpudrive.NO_DRIVER_WARNING not in out.stderr


def test_only_the_driver_line_is_dropped(monkeypatch, capfd):
    def init():
        os.write(2, b"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution will not be "
                    b"available.\n")
        os.write(2, b"some other Warp warning\n")
        print("a Python warning", file=sys.stderr)

    monkeypatch.setattr(tg_gpudrive, "_cuda_driver_loadable", lambda: False)
    monkeypatch.setattr(tg_gpudrive._wp, "init", init)
    tg_gpudrive._init_warp_without_driver_warning()
    err = capfd.readouterr().err
    assert tg_gpudrive.NO_DRIVER_WARNING not in err
    assert "some other Warp warning" in err and "a Python warning" in err
