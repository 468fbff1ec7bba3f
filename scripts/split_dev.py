"""Pack the 61 real WOMD development scenes into two stores, training and held out, by the split of
configs/data/womd_dev_split.yaml (the extract of ../shared/womd_dev/extract writes them):

    python scripts/split_dev.py --src ~/.cache/tg_gpudrive/womd_dev --out ~/.cache/tg_gpudrive

writes <out>/womd_dev_train (44 scenes) and <out>/womd_dev_heldout (17 scenes). With --subsets 5,15,30
it also writes <out>/womd_dev_train_5 ... : nested subsets of the training split (the first N of its
scenes in a fixed order, sha1 of the name), for the curve of held-out rates against the number of real
training scenes.
"""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

import yaml

from tg_gpudrive.config import REPO_CONFIGS
from tg_gpudrive.data.store import convert

SPLIT = REPO_CONFIGS / "data" / "womd_dev_split.yaml"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--src", required=True, help="the folder of the 61 extracted JSON scenes")
    p.add_argument("--out", required=True, help="where the two stores go")
    p.add_argument("--subsets", default="", help="comma-separated sizes of nested training subsets (e.g. 5,15,30)")
    args = p.parse_args(argv)
    sizes = [int(x) for x in args.subsets.split(",") if x.strip()]
    split = yaml.safe_load(SPLIT.read_text())
    src = Path(args.src).expanduser()
    for part in ("train", "heldout"):
        files = [src / name for name in split[part]]
        missing = [f for f in files if not f.is_file()]
        if missing:
            raise SystemExit(f"split_dev: {len(missing)} scene(s) of the {part} split are not in {src} "
                             f"(first: {missing[0].name}); run ../shared/womd_dev/extract first")
        stores = [(f"womd_dev_{part}", files)]
        if part == "train":
            order = sorted(files, key=lambda f: hashlib.sha1(f.name.encode()).hexdigest())
            for n in sizes:
                if not 0 < n <= len(files):
                    raise SystemExit(f"split_dev: --subsets {n}: expected 1..{len(files)}")
                stores.append((f"womd_dev_train_{n}", order[:n]))
        for name, chosen in stores:
            rep = convert(chosen, Path(args.out).expanduser() / name, resume=False, progress=False)
            print(f"{name}: {rep.converted} scenes -> {rep.out} ({len(rep.failed)} failed, "
                  f"{len(rep.unplayable)} unplayable)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
