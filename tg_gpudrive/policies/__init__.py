"""Policies that ship with the package.

`shipped.pt`: a CCE-MAPPO training checkpoint (as `learn.train.Trainer.save` writes it) that
`tg-gpudrive evaluate --checkpoint shipped`, `tg-gpudrive render --policy shipped` and
`tg-gpudrive report --runs shipped` load by name; the name is resolved in one place,
`tg_gpudrive.checkpoint.checkpoint_path` (SHIPPED_POLICY). An install without the file says so
when the name is used. It is `shipped_v1.pt` fine-tuned for 161 updates on every vehicle with a
budget of half the logs' CVaR (BENCHMARKS.md, "The shipped policy fine-tuned on every vehicle").

`shipped_v1.pt`: the policy shipped before (400 updates of configs/train/gpu.yaml), loaded by the name
"shipped_v1" (checkpoint.SHIPPED_EARLIER): the current one and the documented grid started from it.
"""
