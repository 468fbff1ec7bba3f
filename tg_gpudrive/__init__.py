"""tg_gpudrive: TrafficGamer scenario generation on a batched NVIDIA Warp driving engine."""

import ctypes
import os
import sys
import tempfile

import warp as _wp

# the engine never differentiates through its kernels: skipping adjoints halves compile time;
# Warp's banner and per-module load lines would otherwise interleave with --json output
_wp.config.enable_backward = False
_wp.config.log_level = getattr(_wp, "LOG_WARNING", 30)

NO_DRIVER_WARNING = "Could not find or load the NVIDIA CUDA driver"


def _cuda_driver_loadable() -> bool:
    """Whether the CUDA driver library loads, tried as Warp's native init tries it."""
    names = {"win32": ("nvcuda.dll",), "linux": ("libcuda.so", "libcuda.so.1")}.get(sys.platform)
    if names is None:  # no CUDA build of Warp here (macOS): it prints nothing about a driver
        return True
    for name in names:
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            pass
    return False


def _init_warp_without_driver_warning() -> None:
    """On a machine without a CUDA driver, initialise Warp now and drop the one line its C++ init
    prints to stderr about it ("Warp CUDA warning: Could not find or load the NVIDIA CUDA driver.
    GPU execution will not be available."): Warp has no setting for that line, and device "auto"
    already means cpu there. Everything else printed meanwhile is passed on unchanged; where a driver
    loads, or stderr is not a file descriptor, nothing changes (Warp initialises on first use)."""
    if _cuda_driver_loadable():
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (AttributeError, OSError, ValueError):
        return
    with tempfile.TemporaryFile() as tmp:
        try:
            os.dup2(tmp.fileno(), 2)
            _wp.init()
        finally:
            try:
                sys.stderr.flush()
            except (AttributeError, OSError, ValueError):
                pass
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode(errors="replace")
    kept = "".join(line for line in text.splitlines(True) if NO_DRIVER_WARNING not in line)
    if kept:
        sys.stderr.write(kept)
        sys.stderr.flush()


_init_warp_without_driver_warning()

__version__ = "0.1.0"
