"""tg_gpudrive: TrafficGamer scenario generation on a batched NVIDIA Warp driving engine."""

__version__ = "0.1.0"
