"""Every README snippet marked runnable runs as written, on the CPU.

A fenced block preceded by `<!-- test: run -->` runs as it stands; `<!-- test: run shrunk -->` runs with
smaller sizes (SHRINK: fewer updates, worlds, episodes and scenes), so that training commands fit the
suite. Python blocks run in a fresh interpreter; shell blocks line by line under `bash -e`. Both run in a
scratch folder that links the repository's `configs/` and `tests/`, as a checkout would have them.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from test_report_markdown import csv_rows

from tg_gpudrive.evaluation.report_markdown import PER_AGENT_COLUMNS, PER_SCENE_COLUMNS

REPO = Path(__file__).resolve().parent.parent
MARK = re.compile(r"<!-- test: run( shrunk)? -->\n```(\w+)\n(.*?)```", re.S)
# what "shrunk" changes: (pattern, replacement) on each shell line
SHRINK = [
    (re.compile(r"--episodes \d+"), "--episodes 2"),
    (re.compile(r"--num-scenes \d+"), "--num-scenes 2"),
    (re.compile(r"^(tg-gpudrive train .*)$"),
     r"\1 --set updates=2 --set num_worlds=2 --set num_scenes=2 --set rollout_steps=8 --set hidden=32 "
     r"--set quantiles=8"),
    (re.compile(r"^(tg-gpudrive report .*)$"), r"\1 --scenes 2 --top 1"),
    (re.compile(r"^(tg-gpudrive generate .*)$"), r"\1 --seconds 3 --num-scenes 2 --worlds 2 --no-gif"),
]


def snippets() -> list[tuple[str, bool, str, str]]:
    text = (REPO / "README.md").read_text()
    out = []
    for k, m in enumerate(MARK.finditer(text)):
        line = text[: m.start()].count("\n") + 1
        out.append((f"line{line}-{m.group(2)}", bool(m.group(1)), m.group(2), m.group(3)))
    return out


def test_the_readme_marks_its_snippets():
    kinds = [lang for _, _, lang, _ in snippets()]
    assert kinds.count("bash") >= 4 and kinds.count("python") >= 3


def _shrink(line: str) -> str:
    for pat, rep in SHRINK:
        line = pat.sub(rep, line)
    return line


@pytest.mark.parametrize("name,shrunk,lang,body", snippets(), ids=[s[0] for s in snippets()])
def test_readme_snippet_runs(tmp_path, name, shrunk, lang, body):
    for d in ("configs", "tests"):
        (tmp_path / d).symlink_to(REPO / d)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if lang == "python":
        script = tmp_path / "snippet.py"
        script.write_text(body)
        r = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, env=env,
                           timeout=900)
        assert r.returncode == 0, r.stderr[-3000:]
        assert r.stdout.strip(), "a Python snippet should show something"
        return
    assert lang == "bash"
    lines = [ln.split("  #")[0].strip() for ln in body.splitlines()]
    lines = [_shrink(ln) if shrunk else ln for ln in lines if ln and not ln.startswith("#")]
    for ln in lines:
        r = subprocess.run(["bash", "-e", "-c", ln], cwd=tmp_path, capture_output=True, text=True, env=env,
                           timeout=900)
        assert r.returncode == 0, f"{ln}\n{r.stderr[-3000:]}"
        if ln.startswith("tg-gpudrive report"):  # report.md names its tables, written beside it as CSV
            out = tmp_path / re.search(r"--out (\S+)", ln).group(1)
            md = (out / "report.md").read_text()
            assert "(per_agent.csv)" in md and "(per_scene.csv)" in md
            csv_rows(out / "per_agent.csv", PER_AGENT_COLUMNS)
            assert csv_rows(out / "per_scene.csv", PER_SCENE_COLUMNS)
