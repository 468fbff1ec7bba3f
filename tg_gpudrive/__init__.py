"""tg_gpudrive: TrafficGamer scenario generation on a batched NVIDIA Warp driving engine."""

import warp as _wp

# the engine never differentiates through its kernels: skipping adjoints halves compile time;
# Warp's banner and per-module load lines would otherwise interleave with --json output
_wp.config.enable_backward = False
_wp.config.log_level = getattr(_wp, "LOG_WARNING", 30)

__version__ = "0.1.0"
