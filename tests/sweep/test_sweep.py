"""Sweep engine: rows, resume, crash isolation, worker/engine independence, statistics, figures.

The episodes below are deterministic functions of the seed; the expected rows are computed
independently of the sweep code (by hand-flattening the same formula), so a sweep that mixes
up seeds, drops rows, mis-writes values or lets a crash leak into another row fails.
"""

from __future__ import annotations

import csv
import functools
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.sweep import (
    CommandEpisode,
    MissingDependencyError,
    parse_seeds,
    plot_sweep,
    read_rows,
    run_sweep,
    summarize,
    wilson_interval,
)
from harvest_qp.sweep.engines import WORKER_DIED_MESSAGE
from harvest_qp.sweep.results import SweepStore

SEEDS = list(range(10))
RAISING_SEED = 4
DYING_SEED = 7
HANGING_SEED = 2


# ---------------------------------------------------------------------------------------------
# Episodes (module level, so spawned workers and Ray workers import them by name)
# ---------------------------------------------------------------------------------------------


def pure_episode(seed: int) -> dict:
    """A metrics dict shaped like the closed loop's, a pure function of the seed (numpy types included)."""
    success = seed % 3 != 0
    return {
        "seed": seed,
        "success": np.bool_(success),
        "phase_reached": "pre_cut" if success else "bimanual",
        "abort_reason": None if success else ("collision" if seed % 2 else "timeout"),
        "final_distance_to_roi_center": np.float64(0.01 * seed + 0.1 / 3),
        "final_theta_deg": float(seed) * 1.5 - 2.0,
        "t_bimanual_start": 1.25 + seed / 7,
        "qp_failures": np.int64(seed % 4),
        "contacts": {"arm_arm": seed % 2, "arm_vine": 0},
        "stem_torn": bool(seed == 9),
        "q_final": np.array([seed, 0.5]),
    }


def expected_row(seed: int) -> dict:
    """The row ``pure_episode`` must produce, written out by hand (flattened, plain Python types)."""
    success = seed % 3 != 0
    row = {
        "seed": seed,
        "status": "ok",
        "success": success,
        "phase_reached": "pre_cut" if success else "bimanual",
        "final_distance_to_roi_center": 0.01 * seed + 0.1 / 3,
        "final_theta_deg": float(seed) * 1.5 - 2.0,
        "t_bimanual_start": 1.25 + seed / 7,
        "qp_failures": seed % 4,
        "contacts.arm_arm": seed % 2,
        "contacts.arm_vine": 0,
        "stem_torn": seed == 9,
        "q_final": [float(seed), 0.5],
    }
    if not success:
        row["abort_reason"] = "collision" if seed % 2 else "timeout"
    return row


def faulty_episode(seed: int, *, marker_dir: str | None = None) -> dict:
    """``pure_episode``, except that one seed raises and one kills its process; leaves a marker per call."""
    if marker_dir is not None:
        Path(marker_dir, f"seed{seed}-pid{os.getpid()}-{time.monotonic_ns()}").touch()
    if seed == RAISING_SEED:
        raise ValueError(f"bad scene {seed}\nsecond line")
    if seed == DYING_SEED:
        os._exit(3)
    return pure_episode(seed)


def hanging_episode(seed: int) -> dict:
    if seed == HANGING_SEED:
        time.sleep(120)
    return pure_episode(seed)


def expected_rows(seeds) -> list[dict]:
    rows = []
    for seed in seeds:
        if seed == RAISING_SEED:
            rows.append({"seed": seed, "status": "error", "error": "ValueError: bad scene 4 / second line"})
        elif seed == DYING_SEED:
            rows.append({"seed": seed, "status": "died", "error": WORKER_DIED_MESSAGE})
        else:
            rows.append(expected_row(seed))
    return rows


def without_wall_time(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in row.items() if k != "wall_time_s"} for row in rows]


def markers(marker_dir: Path) -> list[int]:
    return sorted(int(p.name.split("-")[0][4:]) for p in marker_dir.iterdir())


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory):
    """One 10-seed sweep on 2 local processes (seed 4 raises, seed 7 calls os._exit)."""
    base = tmp_path_factory.mktemp("local")
    marker_dir = base / "markers"
    marker_dir.mkdir()
    episode = functools.partial(faulty_episode, marker_dir=str(marker_dir))
    result = run_sweep(episode, SEEDS, out_dir=base / "out", workers=2, progress=False)
    return result, episode, marker_dir


# ---------------------------------------------------------------------------------------------
# Local engine
# ---------------------------------------------------------------------------------------------


def test_local_sweep_rows_are_exact(local_sweep):
    """Each row equals the episode's metrics for its own seed (catches seed mix-ups, lost or mangled values)."""
    result, _, _ = local_sweep
    assert without_wall_time(result.rows) == expected_rows(SEEDS)
    # the file on disk, read back by the sweep's reader and by the csv module directly
    assert without_wall_time(read_rows(result.csv_path)) == expected_rows(SEEDS)
    with open(result.csv_path, newline="") as handle:
        raw = list(csv.DictReader(handle))
    assert [int(r["seed"]) for r in raw] == SEEDS
    assert raw[5]["final_distance_to_roi_center"] == repr(0.01 * 5 + 0.1 / 3)  # floats round-trip exactly
    assert raw[3]["abort_reason"] == "collision" and raw[1]["abort_reason"] == ""
    ok = [r for r in raw if r["status"] == "ok"]
    assert all(float(r["wall_time_s"]) >= 0 for r in ok)
    assert list(raw[0])[:4] == ["seed", "status", "error", "wall_time_s"]


def test_crash_isolation(local_sweep):
    """An episode that raises and one whose process dies are recorded; every other seed still runs.

    Catches: a dead worker breaking the pool (as ProcessPoolExecutor does) or a crash being
    recorded against the wrong seed.
    """
    result, _, marker_dir = local_sweep
    statuses = {row["seed"]: row["status"] for row in result.rows}
    assert statuses == {s: ("error" if s == RAISING_SEED else "died" if s == DYING_SEED else "ok") for s in SEEDS}
    assert sorted(result.ran) == SEEDS and result.skipped == []
    assert markers(marker_dir) == SEEDS  # each seed ran exactly once (no retry of the dying seed)
    traceback_text = (result.out_dir / "errors" / f"seed_{RAISING_SEED}.txt").read_text()
    assert "ValueError: bad scene 4" in traceback_text and "faulty_episode" in traceback_text


def test_resume_runs_only_new_seeds(local_sweep, tmp_path):
    """Re-running skips seeds already in sweep.csv (catches a resume that reruns or loses rows)."""
    result, _, _ = local_sweep
    out_dir = tmp_path / "out"
    shutil.copytree(result.out_dir, out_dir)  # the module's sweep stays untouched for the other tests
    marker_dir = tmp_path / "markers"
    marker_dir.mkdir()
    episode = functools.partial(faulty_episode, marker_dir=str(marker_dir))
    again = run_sweep(episode, SEEDS, out_dir=out_dir, workers=2, progress=False)
    assert again.ran == [] and again.skipped == SEEDS
    assert markers(marker_dir) == []  # nothing was run: no episode call at all
    assert again.rows == result.rows
    more = run_sweep(episode, range(12), out_dir=out_dir, workers=2, progress=False)
    assert sorted(more.ran) == [10, 11] and more.skipped == SEEDS
    assert markers(marker_dir) == [10, 11]
    assert without_wall_time(more.rows) == expected_rows(range(12))
    retried = run_sweep(episode, range(12), out_dir=out_dir, workers=2, progress=False, retry_failed=True)
    assert sorted(retried.ran) == [RAISING_SEED, DYING_SEED]
    assert markers(marker_dir) == [RAISING_SEED, DYING_SEED, 10, 11]
    assert without_wall_time(retried.rows) == expected_rows(range(12))


def test_worker_count_does_not_change_rows(local_sweep, tmp_path):
    """One worker gives the same rows as two (catches per-worker seeding or order-dependent results)."""
    result, _, _ = local_sweep
    single = run_sweep(faulty_episode, SEEDS, out_dir=tmp_path, workers=1, progress=False)
    assert without_wall_time(single.rows) == without_wall_time(result.rows)


def sim_episode(seed: int) -> dict:
    """A real MuJoCo episode on the randomised scene of ``seed``: 100 passive steps of the vine scene."""
    import mujoco

    from harvest_qp.sim.scene import VineSceneParams, build_vine_scene

    scene = build_vine_scene(VineSceneParams.sample(seed))
    data = mujoco.MjData(scene.model)
    for _ in range(100):
        mujoco.mj_step(scene.model, data)
    return {
        "stem_base": scene.stem_base.tolist(),
        "ngeom": int(scene.model.ngeom),
        "final_cluster_z": float(data.xpos[scene.ids["cluster"], 2]),
        "final_qpos_norm": float(np.linalg.norm(data.qpos)),
    }


def test_mujoco_episodes_in_workers_match_this_process(tmp_path):
    """MuJoCo episodes run in sweep workers give bit-identical metrics to the same calls in this process.

    Catches: workers whose MuJoCo/numpy state differs from a fresh process (start method, preloading),
    and a seed that does not reach the scene (the scenes must differ between seeds).
    """
    seeds = [0, 1, 2, 3]
    result = run_sweep(sim_episode, seeds, out_dir=tmp_path, workers=2, progress=False)
    expected = [{"seed": s, "status": "ok", **sim_episode(s)} for s in seeds]
    assert without_wall_time(result.rows) == expected
    assert len({tuple(row["stem_base"]) for row in expected}) == len(seeds)


def test_episode_timeout_stops_only_that_episode(tmp_path):
    """A hanging episode is stopped and recorded; its worker is replaced and the next seed still runs."""
    result = run_sweep(
        hanging_episode, [HANGING_SEED, 5], out_dir=tmp_path, workers=1, episode_timeout=1.5, progress=False
    )
    assert result.rows[0] == {
        "seed": HANGING_SEED,
        "status": "timeout",
        "error": "Timeout: the episode ran longer than 1.5 s and its process was stopped",
    }
    assert without_wall_time(result.rows[1:]) == [expected_row(5)]


def test_ctrl_c_keeps_finished_rows_and_leaves_no_process(tmp_path):
    """Ctrl-C on a sweep: finished rows stay in sweep.csv and no worker (not even a hung one) survives.

    Catches: workers orphaned by an interrupted sweep, rows lost on interrupt.
    """
    import signal
    import subprocess

    token = f"harvest-qp-sweep-test-{os.getpid()}-{time.monotonic_ns()}"
    out_dir = tmp_path / "out"
    script = (
        "from harvest_qp.sweep import run_sweep\n"
        "from tests.sweep.test_sweep import hanging_episode\n"
        f"run_sweep(hanging_episode, [0, 1, {HANGING_SEED}, 3], out_dir={str(out_dir)!r}, workers=2, progress=False)\n"
    )
    env = {**os.environ, "HARVEST_QP_TEST_TOKEN": token, "PYTHONPATH": os.pathsep.join(sys.path)}
    # preexec_fn: Ctrl-C as in a terminal, also when pytest runs with SIGINT ignored (a background job of
    # a non-interactive shell, whose children inherit the ignored SIGINT)
    proc = subprocess.Popen([sys.executable, "-c", script], env=env, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and proc.poll() is None:
            csv_path = out_dir / "sweep.csv"
            if csv_path.exists() and len(csv_path.read_text().splitlines()) == 4:  # header + seeds 0, 1, 3
                break
            time.sleep(0.1)
        assert proc.poll() is None, "the sweep ended although seed 2 hangs"
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does: the whole process group
        assert proc.wait(timeout=30) != 0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert [row["seed"] for row in read_rows(out_dir)] == [0, 1, 3]
    deadline = time.monotonic() + 10.0
    while _processes_with_env_value(token) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _processes_with_env_value(token) == []


def test_torn_last_line_is_dropped(tmp_path):
    """A sweep killed mid-write leaves a cut line; it is dropped (that seed runs again), never half-read."""
    (tmp_path / "sweep.csv").write_text("seed,status,final_x\n0,ok,0.125\n1,ok,0.12")
    store = SweepStore(tmp_path)
    assert store.sorted_rows() == [{"seed": 0, "status": "ok", "final_x": 0.125}]
    assert (tmp_path / "sweep.csv").read_text() == "seed,status,final_x\n0,ok,0.125\n"


def test_progress_line(tmp_path):
    """The progress line counts episodes and successes (catches a miscounted or missing progress report)."""

    class Stream:
        text = ""

        def write(self, s):
            self.text += s

        def flush(self):
            pass

    stream = Stream()
    run_sweep(pure_episode, [1, 2, 3], out_dir=tmp_path, workers=2, progress=stream)
    last = stream.text.strip().splitlines()[-1]
    assert last.startswith("sweep: 3/3 episodes done, 2 succeeded (67 %), 0 failed to run")
    assert "ETA 0s" in last


FAKE_RUN = """
import argparse, json, pathlib, sys
parser = argparse.ArgumentParser()
parser.add_argument("config")
parser.add_argument("--seed", type=int)
parser.add_argument("--out")
args = parser.parse_args()
if args.seed == 2:
    sys.exit("scene 2: the stem is out of reach")
out = pathlib.Path(args.out)
out.mkdir(parents=True, exist_ok=True)
if args.seed != 3:
    (out / "metrics.json").write_text(json.dumps({"success": args.seed % 2 == 0, "config": args.config,
                                                  "final_position_error": args.seed / 100}))
if args.seed == 4:
    sys.exit(3)  # crashed after writing its metrics: an error, not a result
sys.exit(0 if args.seed % 2 == 0 or args.seed == 3 else 1)  # as harvest-qp run: 1 = ran, not a success
"""


def test_command_episode_runs_one_process_per_seed(tmp_path):
    """harvest-qp run as a command: its metrics.json becomes the row; a failing command is that seed's error.

    Catches: an unsuccessful episode (exit code 1 with its metrics written, as ``harvest-qp run``
    does) recorded as a crash without its metrics and abort reason."""
    script = tmp_path / "fake_run.py"
    script.write_text(FAKE_RUN)
    episode = CommandEpisode((sys.executable, str(script), "paper.yaml"), runs_dir=str(tmp_path / "runs"))
    result = run_sweep(episode, [0, 1, 2, 3, 4], out_dir=tmp_path / "out", workers=2, progress=False)
    rows = without_wall_time(result.rows)
    assert rows[:2] == [
        {"seed": 0, "status": "ok", "success": True, "config": "paper.yaml", "final_position_error": 0.0},
        {"seed": 1, "status": "ok", "success": False, "config": "paper.yaml", "final_position_error": 0.01},
    ]
    assert rows[2]["status"] == "error" and rows[2]["error"].startswith("EpisodeCommandError: ")
    assert rows[2]["error"].endswith("exited with code 1: scene 2: the stem is out of reach")
    assert rows[3]["status"] == "error" and "wrote no readable" in rows[3]["error"]
    assert rows[4]["status"] == "error" and "exited with code 3" in rows[4]["error"]
    assert (tmp_path / "runs" / "seed_1" / "metrics.json").exists()


def pure_factory(config, runs_dir, overrides=()):
    """An episode factory for ``sweep_main`` (the CLI's default runs ``harvest-qp run`` per seed)."""
    return pure_episode


def test_cli_sweep_subcommand(tmp_path, capsys):
    """`harvest-qp sweep CONFIG --seeds 0:4 --workers 2 --out DIR` as the CLI will mount it."""
    import argparse

    from harvest_qp.sweep.cli import add_sweep_parser, sweep_main

    parser = argparse.ArgumentParser(prog="harvest-qp")
    add_sweep_parser(parser.add_subparsers(dest="command"))
    config = tmp_path / "paper.yaml"
    config.write_text("episode: {duration: 1.0}\n")
    argv = ["sweep", str(config), "--seeds", "0:4", "--workers", "2", "--out", str(tmp_path / "out"), "--quiet"]
    assert sweep_main(parser.parse_args(argv), episode_for=pure_factory) == 0
    out = capsys.readouterr().out
    assert out.startswith("2/4 episodes succeeded (50.0 %, 95 % CI ")  # seeds 1 and 2 succeed
    assert "ran 4, skipped 0 already done" in out
    assert without_wall_time(read_rows(tmp_path / "out")) == [expected_row(s) for s in range(4)]
    config.write_text("episode: {duration: 2.0}\n")  # another experiment: refused, not mixed in
    with pytest.raises(InvalidInputError, match="another experiment"):
        sweep_main(parser.parse_args(argv), episode_for=pure_factory)
    with pytest.raises(InvalidInputError, match="is not a file"):
        sweep_main(parser.parse_args(["sweep", str(tmp_path / "missing.yaml")]), episode_for=pure_factory)


def test_cli_sweep_set_reaches_every_episode_and_the_fingerprint(tmp_path):
    """`harvest-qp sweep CONFIG --set camera.frame_loss=0.3`: each episode's command carries the override,
    the experiment's fingerprint is that of the overridden settings, and a bad key fails before any episode."""
    import argparse

    from harvest_qp.config.settings import load_settings
    from harvest_qp.exceptions import ConfigError
    from harvest_qp.sweep.cli import add_sweep_parser, config_fingerprint, run_command_episode, sweep_main

    parser = argparse.ArgumentParser(prog="harvest-qp")
    add_sweep_parser(parser.add_subparsers(dest="command"))
    config = tmp_path / "paper.yaml"
    config.write_text("episode: {duration: 1.0}\n")
    seen = []

    def factory(config_path, runs_dir, overrides=()):
        seen.append(run_command_episode(config_path, runs_dir, overrides).argv)
        return pure_episode

    argv = ["sweep", str(config), "--seeds", "0:2", "--workers", "1", "--out", str(tmp_path / "out"), "--quiet",
            "--set", "camera.frame_loss=0.3", "--set", "force_sensor.noise_std=0.2"]
    assert sweep_main(parser.parse_args(argv), episode_for=factory) == 0
    assert seen[0][-4:] == ("--set", "camera.frame_loss=0.3", "--set", "force_sensor.noise_std=0.2")
    overridden = load_settings(config, ["camera.frame_loss=0.3", "force_sensor.noise_std=0.2"])
    assert overridden.camera.frame_loss == 0.3 and overridden.force_sensor.noise_std == 0.2
    plain, faulty = config_fingerprint(config), config_fingerprint(config, ("camera.frame_loss=0.3",))
    assert plain["settings_sha256"] != faulty["settings_sha256"]
    with pytest.raises(ConfigError, match="frame_los"):
        sweep_main(parser.parse_args([*argv[:8], "--set", "camera.frame_los=0.3"]), episode_for=factory)
    assert len(seen) == 1  # the bad key stopped the sweep before any episode


# ---------------------------------------------------------------------------------------------
# Report and statistics
# ---------------------------------------------------------------------------------------------


def test_wilson_interval_hand_computed_and_scipy():
    """8/10: Wilson 95 % = (0.4902, 0.9433) by hand; also against scipy's binomtest (catches Wald or wrong z)."""
    import scipy.stats  # here, not at the top: sweep workers import this module for its episodes

    low, high = wilson_interval(8, 10)
    z = 1.959963984540054
    p, n = 0.8, 10
    center = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    assert (low, high) == pytest.approx((center - half, center + half), abs=1e-12)
    assert (low, high) == pytest.approx((0.49016, 0.94332), abs=1e-5)
    for k, n in [(0, 10), (10, 10), (37, 100), (1, 3)]:
        ci = scipy.stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        assert wilson_interval(k, n) == pytest.approx((ci.low, ci.high), abs=1e-9)
    assert all(math.isnan(v) for v in wilson_interval(0, 0))
    with pytest.raises(InvalidInputError, match="successes"):
        wilson_interval(11, 10)


def test_report_counts_and_medians(local_sweep):
    """sweep.md: success count, Wilson interval, failure reasons and medians match values computed here."""
    result, _, _ = local_sweep
    ok = [s for s in SEEDS if s not in (RAISING_SEED, DYING_SEED)]
    successes = [s for s in ok if s % 3 != 0]
    summary = result.summary
    assert summary.episodes == 10 and summary.successes == len(successes) == 4
    assert summary.interval == pytest.approx(wilson_interval(4, 10))
    # seeds 0, 6 -> timeout, 3, 9 -> collision, 4 raised, 7 died
    assert dict(summary.failure_reasons) == {
        "timeout": 2,
        "collision": 2,
        "error: ValueError": 1,
        "worker died": 1,
    }
    medians = {m.name: m for m in summary.medians}
    theta = [float(s) * 1.5 - 2.0 for s in ok]
    assert medians["final_theta_deg"].median == pytest.approx(float(np.median(theta)))
    assert medians["final_theta_deg"].count == len(ok)
    assert "success" not in medians and summary.fractions["stem_torn"] == (1, len(ok))
    text = result.report_path.read_text()
    assert "**Success: 4 / 10 episodes = 40.0 %**" in text
    low, high = wilson_interval(4, 10)
    assert f"95 % Wilson interval {100 * low:.1f} % to {100 * high:.1f} %" in text
    assert "| error: ValueError | 1 |" in text and "| worker died | 1 |" in text
    assert summarize(read_rows(result.out_dir)).failure_reasons == summary.failure_reasons


def test_figures_plot_present_metrics_and_skip_missing(local_sweep, tmp_path):
    """The figures plot exactly the per-seed values of the metrics present; missing ones are skipped."""
    result, _, _ = local_sweep
    ok = [s for s in SEEDS if s not in (RAISING_SEED, DYING_SEED)]
    assert set(result.figures.paths) == {"sweep_final_errors", "sweep_times"}
    assert result.figures.plotted["final_distance_to_roi_center"] == [0.01 * s + 0.1 / 3 for s in ok]
    assert result.figures.plotted["t_bimanual_start"] == [1.25 + s / 7 for s in ok]
    for path in result.figures.paths.values():
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    figures = plot_sweep(
        result.rows, tmp_path, error_metrics=["final_theta_deg", "final_alignment_deg"], time_metrics=["t_precut"]
    )
    assert list(figures.plotted) == ["final_theta_deg"]
    assert figures.skipped == ["final_alignment_deg", "t_precut"]
    assert list(figures.paths) == ["sweep_final_errors"] and not (tmp_path / "sweep_times.png").exists()


# ---------------------------------------------------------------------------------------------
# Input checks
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("spec", "seeds"),
    [
        ("0:5", [0, 1, 2, 3, 4]),
        ("3", [3]),
        ("1,2,5", [1, 2, 5]),
        ("0:10:2", [0, 2, 4, 6, 8]),
        (" 7:9 , 20", [7, 8, 20]),
    ],
)
def test_parse_seeds(spec, seeds):
    assert parse_seeds(spec) == seeds


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("", "must not be empty"),
        ("-1", "'-1' in '-1' is not a non-negative integer"),
        ("a:5", "'a'"),
        ("5:5", "is empty"),
        ("9:3", "is empty"),
        ("0:10:0", "step 0"),
        ("1:2:3:4", "4 fields"),
        ("1,1", "seed 1 appears more than once"),
        ("1.5", "'1.5'"),
        ("1,,2", "''"),
    ],
)
def test_parse_seeds_rejects_bad_input(spec, match):
    with pytest.raises(InvalidInputError, match=match):
        parse_seeds(spec)


def test_run_sweep_rejects_bad_arguments(tmp_path):
    with pytest.raises(InvalidInputError, match="engine must be one of"):
        run_sweep(pure_episode, [0], out_dir=tmp_path, engine="dask")
    with pytest.raises(InvalidInputError, match="workers must be a positive integer"):
        run_sweep(pure_episode, [0], out_dir=tmp_path, workers=0)
    with pytest.raises(InvalidInputError, match="address is for engine='ray'"):
        run_sweep(pure_episode, [0], out_dir=tmp_path, address="10.0.0.1:6379")
    with pytest.raises(InvalidInputError, match="episode must be picklable"):
        run_sweep(lambda seed: {}, [0], out_dir=tmp_path)
    with pytest.raises(InvalidInputError, match="seed 3 appears more than once"):
        run_sweep(pure_episode, [3, 3], out_dir=tmp_path)
    assert not (tmp_path / "sweep.csv").exists()


def test_other_experiment_in_folder_is_refused(tmp_path):
    """A folder holding a sweep of another config is not resumed into (catches mixed experiments)."""
    run_sweep(pure_episode, [1], out_dir=tmp_path, workers=1, progress=False, fingerprint={"config": "a.yaml"})
    with pytest.raises(InvalidInputError, match="another experiment"):
        run_sweep(pure_episode, [1], out_dir=tmp_path, workers=1, progress=False, fingerprint={"config": "b.yaml"})


def test_ray_missing_names_the_extra(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # makes `import ray` raise ImportError
    with pytest.raises(MissingDependencyError, match=r'pip install -e "\.\[cluster\]"'):
        run_sweep(pure_episode, [0], out_dir=tmp_path, engine="ray")
    assert not (tmp_path / "sweep.csv").exists()


# ---------------------------------------------------------------------------------------------
# Ray
# ---------------------------------------------------------------------------------------------


def _processes_with_env_value(value: str) -> list[int]:
    """PIDs whose initial environment contains ``value`` (the local Ray instance's token)."""
    needle = value.encode()
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if needle in (entry / "environ").read_bytes():
                    found.append(int(entry.name))
            except OSError:  # gone, or not ours to read
                pass
    return found


def test_ray_sweep_matches_local_row_for_row(local_sweep, tmp_path, monkeypatch):
    """The same seeds as Ray tasks on a private local instance give the local rows, crash rows included.

    Catches: Ray retrying the dying seed, an engine-dependent row, an episode exception escaping,
    and a local instance that leaves its processes, its session folder or ``~/.ray/auth_token`` behind.
    """
    from harvest_qp.sweep import engines

    result, _, _ = local_sweep
    token_file = Path.home() / ".ray" / "auth_token"
    had_token_file = token_file.exists()
    # A private, short temp folder (Ray's socket paths must fit in 107 bytes): a sweep of
    # another process running at the same time (a second test session) cannot add to it.
    private_tmp = tempfile.mkdtemp(prefix="hqt-")
    monkeypatch.setattr(tempfile, "tempdir", private_tmp)
    temp_before = set(Path(tempfile.gettempdir()).glob("hqray-*"))
    assert "RAY_AUTH_TOKEN" not in os.environ  # else the instance would use the caller's token
    marker_dir = tmp_path / "markers"
    marker_dir.mkdir()
    episode = functools.partial(faulty_episode, marker_dir=str(marker_dir))
    ray_result = run_sweep(episode, SEEDS, out_dir=tmp_path / "out", engine="ray", workers=2, progress=False)
    assert without_wall_time(ray_result.rows) == without_wall_time(result.rows)
    assert markers(marker_dir) == SEEDS  # each seed ran once: the dying seed was not retried
    assert ray_result.summary.failure_reasons == result.summary.failure_reasons
    assert token_file.exists() == had_token_file
    assert set(Path(tempfile.gettempdir()).glob("hqray-*")) == temp_before
    assert "RAY_AUTH_TOKEN" not in os.environ and "RAY_AUTH_MODE" not in os.environ
    deadline = time.monotonic() + 15.0
    while _processes_with_env_value(engines._LOCAL_RAY_TOKEN) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _processes_with_env_value(engines._LOCAL_RAY_TOKEN) == []
    shutil.rmtree(private_tmp, ignore_errors=True)


def test_ray_cluster_auth_failure_names_the_fix(monkeypatch, tmp_path):
    """Connecting to a token-auth cluster without RAY_AUTH_MODE=token: the error says what to set.

    (Ray 2.60 enables tokens from RAY_AUTH_TOKEN only for address='auto'; measured against a
    `ray start --head` cluster, see notes/sweep.md.)
    """
    import ray

    from harvest_qp.sweep import SweepEngineError

    def refuse(*args, **kwargs):
        try:
            raise RuntimeError("Failed to connect to GCS. ray.exceptions.AuthenticationError: InvalidAuthToken")
        except RuntimeError as cause:
            raise ConnectionError("Failed to connect to Ray cluster at 10.0.0.5:6379") from cause

    monkeypatch.setattr(ray, "init", refuse)
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    with pytest.raises(SweepEngineError, match="set RAY_AUTH_MODE=token and RAY_AUTH_TOKEN"):
        run_sweep(pure_episode, [0], out_dir=tmp_path, engine="ray", address="10.0.0.5:6379", progress=False)


def none_metric_episode(seed: int) -> dict:
    return {"success": True, "abort_reason": None, "final_position_error": seed / 1000}


def test_a_metric_that_is_none_in_every_row_keeps_its_column(tmp_path):
    """Every metric of metrics.json has a column, even one that is None in every episode (the
    audit found no abort_reason column in a sweep where nothing aborted)."""
    result = run_sweep(none_metric_episode, [1, 2], out_dir=tmp_path, workers=1, progress=False)
    with open(result.csv_path, newline="") as handle:
        raw = list(csv.DictReader(handle))
    assert [r["abort_reason"] for r in raw] == ["", ""]
    assert without_wall_time(read_rows(result.csv_path)) == without_wall_time(result.rows)
