"""Policies that ship with the package.

`shipped.pt`: a CCE-MAPPO training checkpoint (as `learn.train.Trainer.save` writes it) that
`tg-gpudrive evaluate --checkpoint shipped`, `tg-gpudrive render --policy shipped` and
`tg-gpudrive report --runs shipped` load by name; the name is resolved in one place,
`tg_gpudrive.checkpoint.checkpoint_path` (SHIPPED_POLICY). An install without the file says so
when the name is used.
"""
