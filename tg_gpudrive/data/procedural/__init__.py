"""Procedural safety-critical scenarios, the embedded default scene source (`generator`: settings,
retries and export; `geometry`: roads; `traffic`: the human-like drive; `checks`: invariants)."""

from tg_gpudrive.data.procedural.generator import SCENARIO_TYPES, ProceduralParams, generate_scene, generate_scenes

__all__ = ["SCENARIO_TYPES", "ProceduralParams", "generate_scene", "generate_scenes"]
