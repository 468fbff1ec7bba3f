"""Fill W worlds with scenes from a `SceneSource`, deterministically and resumably.

Without replacement the sampler walks a permutation of all scene indices
(permutation e is drawn from ``(seed, e)``), starting the next permutation when
one runs out, so every scene is visited once before any repeats (across a
wrap, scenes of the old and new permutation can share one draw). With
replacement draw k is ``W`` uniform indices from ``(seed, k)``. Either way the
whole position is a few integers, so `state_dict()` / `load_state_dict()`
resume a training run exactly.

Resampling cadence is the caller's: build worlds from `sample()` once, then
call it again whenever ``SceneSampler.should_resample(step, every_n)`` is true.
This module never builds engine arrays; it only picks scenes.
"""

from __future__ import annotations

import numpy as np

from tg_gpudrive.scene import Scene


class SceneSampler:
    """Draw `num_worlds` scene indices per call from `source` (anything with `len` and `get`).

    Attributes:
        last_indices  (num_worlds,) int64  indices of the latest draw (empty before the first)
        draws         int                  number of draws so far
        visited       int                  distinct scene indices drawn so far
    """

    def __init__(self, source, num_worlds: int, *, replacement: bool, seed: int):
        self.source = source
        self.num_scenes = int(len(source))
        if self.num_scenes <= 0:
            raise ValueError(f"scene source {getattr(source, 'name', source)!r} is empty")
        if int(num_worlds) <= 0:
            raise ValueError(f"num_worlds must be positive, got {num_worlds}")
        self.num_worlds = int(num_worlds)
        self.replacement = bool(replacement)
        self.seed = int(seed)
        self.draws = 0
        self._epoch = 0  # permutation number (without replacement)
        self._cursor = 0  # position in that permutation
        self._perm: np.ndarray | None = None
        self._perm_epoch = -1
        self._visited = np.zeros(self.num_scenes, bool)
        self._num_visited = 0
        self.last_indices = np.zeros(0, np.int64)

    # -------------------------------------------------------------- drawing
    def _permutation(self, epoch: int) -> np.ndarray:
        if self._perm is None or self._perm_epoch != epoch:
            self._perm = np.random.default_rng([self.seed, epoch]).permutation(self.num_scenes)
            self._perm_epoch = epoch
        return self._perm

    def sample_indices(self) -> np.ndarray:
        """Next (num_worlds,) int64 scene indices; advances the sampler."""
        w = self.num_worlds
        if self.replacement:
            idx = np.random.default_rng([self.seed, self.draws]).integers(0, self.num_scenes, w)
        else:
            parts, need = [], w
            while need:
                perm = self._permutation(self._epoch)
                take = perm[self._cursor : self._cursor + need]
                parts.append(take)
                need -= len(take)
                self._cursor += len(take)
                if self._cursor == self.num_scenes:
                    self._epoch, self._cursor = self._epoch + 1, 0
            idx = np.concatenate(parts)
        idx = idx.astype(np.int64)
        self.draws += 1
        new = ~self._visited[idx]
        if new.any():
            self._visited[idx] = True
            self._num_visited = int(self._visited.sum())
        self.last_indices = idx
        return idx

    def sample(self) -> list[Scene]:
        """Next `num_worlds` scenes (materialised through ``source.get_many`` when the source has it)."""
        idx = [int(i) for i in self.sample_indices()]
        if hasattr(self.source, "get_many"):
            return self.source.get_many(idx)
        return [self.source.get(i) for i in idx]

    @property
    def visited(self) -> int:
        return self._num_visited

    @property
    def epoch(self) -> int:
        """Completed passes over all scenes (without replacement)."""
        return self._epoch

    @staticmethod
    def should_resample(step: int, every_n: int) -> bool:
        """True on steps every_n, 2 every_n, ... (never for every_n <= 0; step 0 is the initial fill)."""
        return every_n > 0 and step > 0 and step % every_n == 0

    # ---------------------------------------------------------------- state
    def state_dict(self) -> dict:
        """Plain-Python position (ints, bools, a hex string): JSON-, YAML- and torch.save-able."""
        return {
            "num_scenes": self.num_scenes,
            "num_worlds": self.num_worlds,
            "replacement": self.replacement,
            "seed": self.seed,
            "draws": self.draws,
            "epoch": self._epoch,
            "cursor": self._cursor,
            "visited": np.packbits(self._visited).tobytes().hex(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Resume from `state_dict()`. The seed is taken from `state`; num_worlds may differ.

        Raises ValueError if the state belongs to a source of another size or to
        the other replacement mode.
        """
        if int(state["num_scenes"]) != self.num_scenes:
            raise ValueError(f"sampler state is for {state['num_scenes']} scenes, source has {self.num_scenes}")
        if bool(state["replacement"]) != self.replacement:
            raise ValueError(f"sampler state has replacement={state['replacement']}, "
                             f"sampler has replacement={self.replacement}")
        self.seed = int(state["seed"])
        self.draws = int(state["draws"])
        self._epoch, self._cursor = int(state["epoch"]), int(state["cursor"])
        self._perm = None
        bits = np.frombuffer(bytes.fromhex(state["visited"]), np.uint8)
        self._visited = np.unpackbits(bits, count=self.num_scenes).astype(bool)
        self._num_visited = int(self._visited.sum())
        self.last_indices = np.zeros(0, np.int64)
