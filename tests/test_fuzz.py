"""Fuzzing the loaders: random damage to a real WOMD scene never gives a traceback: the source
opens with a scene that validates (and steps), or refuses with one ValueError line that names the
file. Formats: GPUDrive JSON (byte damage), a WOMD TFRecord whose Scenario payload is damaged but
re-framed with valid CRCs (so the protobuf decoder sees the damage), and a gzipped TFRecord with
raw byte damage (gzip and CRC checks)."""

from __future__ import annotations

import gzip

import numpy as np
import pytest
from conftest import WOMD_FILES

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.womd.scenario_proto import write_tfrecord_scenes
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.data.womd.tfrecord import iter_records, write_records
from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
from tg_gpudrive.engine.simulator import Simulator

CASES = 120  # per format, seeded


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    b = bytearray(data)
    kind = rng.integers(4)
    if kind == 0:  # flip one byte
        b[int(rng.integers(0, len(b)))] ^= int(rng.integers(1, 256))
    elif kind == 1:  # cut the file short
        b = b[: int(rng.integers(0, len(b)))]
    elif kind == 2:  # insert junk
        i = int(rng.integers(0, len(b)))
        b[i:i] = rng.integers(0, 256, size=int(rng.integers(1, 16))).astype(np.uint8).tobytes()
    else:  # change digits in place: JSON stays parseable, numbers (ids, types, coordinates) change
        digits = np.flatnonzero(np.frombuffer(bytes(b), np.uint8) - ord("0") < 10)
        for i in rng.choice(digits, size=min(len(digits), int(rng.integers(1, 6))), replace=False):
            b[i] = int(rng.integers(ord("0"), ord("9") + 1))
    return bytes(b)


@pytest.fixture(scope="module")
def originals(tmp_path_factory) -> dict[str, bytes]:
    d = tmp_path_factory.mktemp("orig")
    json_bytes = WOMD_FILES[1].read_bytes()  # the smaller scene
    scene = load_gpudrive_json(WOMD_FILES[1])
    rec = d / "s.tfrecord"
    write_tfrecord_scenes(rec, [scene])
    (payload,) = list(iter_records(rec))
    return {"json": json_bytes, "payload": payload, "tfrecord.gz": gzip.compress(rec.read_bytes())}


@pytest.mark.parametrize("fmt", ["json", "tfrecord", "tfrecord.gz"])
def test_damaged_files_give_a_scene_or_a_one_line_error(fmt, originals, tmp_path):
    rng = np.random.default_rng({"json": 1, "tfrecord": 2, "tfrecord.gz": 3}[fmt])
    opened = refused = 0
    for case in range(CASES):
        path = tmp_path / f"case{case}.{fmt}"
        if fmt == "tfrecord":  # damage the Scenario payload, keep the framing valid
            write_records(path, [mutate(originals["payload"], rng)])
        else:
            path.write_bytes(mutate(originals[fmt], rng))
        try:
            src = resolve_scenes(str(path))
        except ValueError as e:
            msg = str(e)
            assert "\n" not in msg and str(path) in msg, (case, msg)
            refused += 1
            continue
        scene = src.get(0)
        scene.validate()
        opened += 1
        if opened % 15 == 1:  # what opens must also build and step
            sim = Simulator([scene], EngineConfig(max_agents=128, partner_k=4, road_k=8), "cpu")
            sim.reset()
            sim.step()
        path.unlink()
    print(f"{fmt}: {opened} opened, {refused} refused")
    assert refused > 0 and opened + refused == CASES
