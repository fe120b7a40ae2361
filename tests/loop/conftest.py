"""Episodes from the CLI's own code path, shared by the loop tests (each runs once per session)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from harvest_qp.cli import main
from harvest_qp.robot.paths import tasks_dir

PAPER = tasks_dir() / "paper.yaml"
#: The settings every scene test runs with (see tests/loop/test_paper_scenes.py for why).
SCENE_ARGS: tuple[str, ...] = ("--set", "camera.downsample=6", "--set", "perception.min_stem_points=6",
                               "--set", "episode.end_after_precut=2.0")


@pytest.fixture(scope="session")
def cli_episode(tmp_path_factory):
    """``run(seed, *args, figures=False) -> (exit code, metrics, log, out dir)`` of
    ``harvest-qp run tasks/paper.yaml --seed seed *args``; the same call runs once per session."""
    cache: dict[tuple, tuple] = {}

    def run(seed: int, *args: str, figures: bool = False):
        key = (seed, args)
        if key in cache and (cache[key][4] or not figures):
            return cache[key][:4]
        out = tmp_path_factory.mktemp(f"paper-{seed}")
        code = main(["run", str(PAPER), "--seed", str(seed), "--out", str(out), *args,
                     *([] if figures else ["--no-figures"])])
        metrics = json.loads((out / "metrics.json").read_text())
        log = dict(np.load(out / "episode.npz"))
        cache[key] = (code, metrics, log, out, figures)
        return code, metrics, log, out

    run.scene_args = SCENE_ARGS
    return run
