"""Warp kernels of the engine, one module per concern (installed as tg_gpudrive.kernels).

Kernels are pure functions of flat arrays; the launchers that unpack the
engine's Model / State live beside them. Nothing here allocates per step.
"""
