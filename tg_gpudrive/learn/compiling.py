"""The passes that `compile_rollout` sends through torch.compile, with the pass as it is behind them; and the
compiler's start-up, loaded while a trainer builds its worlds.

A compilation is a speed-up, never a condition of training: the compiler fails on some shapes and backends
(inductor's CPU code generator has rejected a dynamic-size pass that the GPU's compiles), and such a failure
is logged once, after which the pass runs as it is for the rest of the run. An error of the pass itself then
comes from its plain run, with its own message.
"""

from __future__ import annotations

import logging
import threading

import torch

log = logging.getLogger(__name__)


class Compiled:
    """`fn` through torch.compile, or `fn` itself once a compiled call has failed. `dynamic`: the (argument,
    dimension) pairs whose sizes change from call to call (an argument by position or keyword), compiled as
    symbolic sizes from the first call; every other size, and every Python number, is compiled as a constant,
    which keeps the tracing short (a fully dynamic compile traces each graph twice, to undo its symbolic floats)."""

    def __init__(self, fn, name: str, dynamic: tuple[tuple[int | str, int], ...] = ()):
        self.fn, self.name, self.dynamic = fn, name, dynamic
        self.compiled = torch.compile(fn)

    def __call__(self, *args, **kwargs):
        if self.compiled is not None:
            for key, dim in self.dynamic:
                torch._dynamo.maybe_mark_dynamic(args[key] if isinstance(key, int) else kwargs[key], dim)
            try:
                return self.compiled(*args, **kwargs)
            except torch.cuda.OutOfMemoryError:  # the device's limit, not the compiler's: the plain pass needs it too
                raise
            except Exception as e:  # noqa: BLE001 - any compiler failure; the plain run below re-raises real errors
                reason = (str(e).strip().splitlines() or [""])[0][:200]
                log.warning("the %s could not be compiled (%s: %s); it runs without compilation from now on",
                            self.name, type(e).__name__, reason)
                self.compiled = None
        return self.fn(*args, **kwargs)


def start_compiler_preload(device: str) -> threading.Thread:
    """The compiler's first use, on a thread of its own (started here; join it): a tiny function compiled and
    differentiated on `device`.

    torch.compile imports some hundred modules on its first call (Dynamo, Inductor, sympy, Triton's runtime on a
    GPU) and sets up its caches; a first update that compiles its loss waits for all of that. Started before the
    worlds are built, most of it happens while the main thread waits for the scene workers; joined before the
    first update, so that the trainer's own compilation never runs beside it. A failure here is logged, never
    raised: the real compilation then meets it with its own message (or `Compiled`'s fallback)."""

    def run() -> None:
        try:
            x = torch.ones(8, device=device, requires_grad=True)
            torch._dynamo.mark_dynamic(x, 0)  # the symbolic sizes' machinery too, as the loss's row count uses
            torch.compile(_preload_fn)(x).backward()
        except Exception as e:  # noqa: BLE001 - a warm-up only: the trainer's compilation reports real faults
            log.warning("the compiler's start-up failed on %s (%s: %s); the first compilation meets it again",
                        device, type(e).__name__, e)

    thread = threading.Thread(target=run, name="compiler-preload", daemon=True)
    thread.start()
    return thread


def _preload_fn(x: torch.Tensor) -> torch.Tensor:
    return (x.sin() * x).sum()
