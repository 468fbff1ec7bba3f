"""Policies that ship with the package.

`shipped.pt`: a CCE-MAPPO policy (config, actor, critic, multipliers) that
`tg-gpudrive evaluate --checkpoint shipped`, `tg-gpudrive render --policy shipped` and
`tg-gpudrive report --runs shipped` load by name; the name is resolved in one place,
`tg_gpudrive.checkpoint.checkpoint_path` (SHIPPED_POLICY). An install without the file says so
when the name is used. It drives real WOMD traffic: trained from scratch with
configs/train/real_mix.yaml on real scenes mixed with urban procedural ones (crossing pedestrians among
them), observing 16 partners and 64 road segments of roads simplified to 0.1 m (its `provenance` field says
how it was made). It acts at temperature 0.5 (its config's act_temperature), chosen after training on its
training scenes.

Earlier policies stay loadable by name (checkpoint.SHIPPED_EARLIER), for comparison:
`shipped_v4.pt`, the policy shipped before (the same recipe without the crossing pedestrians and the
time-to-collision charge); `shipped_v3.pt`, the one before it (`shipped_v2.pt` fine-tuned on the same mix of real and
procedural scenes); `shipped_v2.pt`, trained on procedural scenes only (`shipped_v1.pt` fine-tuned for
161 updates on every vehicle with a budget of half the logs' CVaR); and `shipped_v1.pt` (400 updates of
configs/train/gpu.yaml), which the documented grid started from.
"""
