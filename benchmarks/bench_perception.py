"""Per-frame perception pipeline: harvest_qp.perception next to a brute-force version.

The frame is a ray-cast synthetic vine scene (:mod:`harvest_qp.perception.synthetic`): a
6 cm bent stem hanging from a branch, a 60-berry cluster, four leaves (one partly in front
of the stem) and a background wall, seen by a D415-like camera 0.25 m from the stem base,
at 283x160 (the paper's 848x480 downsampled by 3) and at 848x480.

Timed, side by side in one process:

* ``pipeline``: :func:`harvest_qp.perception.process_cloud`, i.e. classification, stem
  model and p_sb, free space and p_gd (Fibonacci inverse mapping, KD-tree argmax), and the
  unveiling pairs over all non-stem points with V_cu (culled, bundled kernel);
* ``bruteforce``: the same equations written straightforwardly: boolean-mask
  classification, the same stem model, exhaustive nearest-sample search, brute-force
  argmax for ``eq:attr_point``, and the dense O(n_S n_O) ``eq:nearest`` kernel over every
  stem point and every non-stem point.  Too slow to repeat at 848x480 (10^9 pairs), so it
  runs there only with ``--bruteforce-848``.
* scikit-learn's KMeans / NearestNeighbors stand-ins when scikit-learn is importable
  (it is not a dependency; skipped otherwise).

Both versions must agree (same p_sb, p_gd of ``eq:attr_point``, pairs and V_cu); the script
checks this and fails loudly otherwise.  The pipeline's default p_gd (the clearance selection
of :mod:`harvest_qp.perception.free_space`) is timed on its own line.

Lab frames (``--lab``): the same stages on frames of the MuJoCo lab's ray-cast camera
(default scene, 0.35 m from the stem) at 283x160 and 848x480.

Accuracy (``--accuracy``): p_sb, l and p_gd against the lab's ground truth over lab views
0.3-0.45 m from the stem (:class:`harvest_qp.sim.lab_views.LabViews`), the figures of
the notes; ``--seeds`` sets how many sampled scenes (12 views each).

BLAS is limited to one thread (set before numpy loads), as in the other benchmarks: on a
2-core machine running other loops, multi-threaded BLAS calls on small matrices stall and
inflate the timings 2-3x.

Usage::

    python benchmarks/bench_perception.py [--repeats 30] [--bruteforce-848] [--lab] [--accuracy [--seeds 40]]

The last line printed is one JSON object with ``pipeline_ms_283x160``,
``pipeline_ms_848x480``, ``bruteforce_ms_283x160`` (and ``bruteforce_ms_848x480`` when
run), the speed-up ratios and the frame sizes.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402

from harvest_qp.perception import (  # noqa: E402
    classify,
    fibonacci_sphere,
    fit_stem,
    process_cloud,
    ray_obstacle_pairs,
)
from harvest_qp.perception.free_space import compute_free_space  # noqa: E402
from harvest_qp.perception.synthetic import VineScene, render_scene  # noqa: E402
from harvest_qp.references.unveiling import unveiling_velocity  # noqa: E402

D_A, D_O, K_C, N_SAMPLES = 0.01, 0.001, 0.00025, 500
TARGET_MS = {"283x160": 10.0, "848x480": 33.0}
RESOLUTIONS = {"283x160": (283, 160), "848x480": (848, 480)}


@dataclass
class Frame:
    points: np.ndarray
    stem_mask: np.ndarray
    camera: np.ndarray
    gripper: np.ndarray


def make_frame(width: int, height: int) -> Frame:
    scene = VineScene.default()
    camera = scene.stem_base + np.array([0.25, 0.02, -0.04])
    rendered = render_scene(scene, camera, width=width, height=height)
    return Frame(rendered.points, rendered.stem_mask, camera, scene.stem_end + np.array([0.0, 0.0, -0.05]))


def median_ms(function, repeats: int) -> tuple[float, object]:
    result = function()  # warm-up (caches, page faults)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times)), result


# ------------------------------------------------------------------ the fast pipeline


def pipeline(frame: Frame, target_selection: str = "paper"):
    return process_cloud(
        frame.points,
        frame.stem_mask,
        camera_position=frame.camera,
        gripper_position=frame.gripper,
        target_selection=target_selection,
    )


def pipeline_stages(frame: Frame, repeats: int) -> dict[str, float]:
    """Median time of each stage of :func:`process_cloud`, called one by one."""
    split = classify.split_scene(frame.points, frame.stem_mask)
    stem = fit_stem(split.stem, frame.gripper, camera_position=frame.camera, non_stem_points=split.non_stem)
    obstacles = classify.obstacles_near_stem_base(split.non_stem, stem.base, stem.length)
    pairs = ray_obstacle_pairs(split.stem, split.non_stem, frame.camera, d_a=D_A, d_o=D_O)
    return {
        "classification": median_ms(lambda: classify.split_scene(frame.points, frame.stem_mask), repeats)[0],
        "stem model (points only)": median_ms(lambda: fit_stem(split.stem, frame.gripper), repeats)[0],
        "stem model + quality": median_ms(
            lambda: fit_stem(split.stem, frame.gripper, camera_position=frame.camera, non_stem_points=split.non_stem),
            repeats,
        )[0],
        "grasp obstacles": median_ms(
            lambda: classify.obstacles_near_stem_base(split.non_stem, stem.base, stem.length), repeats
        )[0],
        "p_gd eq:attr_point": median_ms(
            lambda: compute_free_space(obstacles, stem.base, stem.length, frame.camera, n_samples=N_SAMPLES),
            repeats,
        )[0],
        "p_gd selection": median_ms(
            lambda: compute_free_space(
                obstacles, stem.base, stem.length, frame.camera, n_samples=N_SAMPLES, scene_points=split.non_stem
            ),
            repeats,
        )[0],
        "unveiling pairs": median_ms(
            lambda: ray_obstacle_pairs(split.stem, split.non_stem, frame.camera, d_a=D_A, d_o=D_O), repeats
        )[0],
        "V_cu": median_ms(lambda: unveiling_velocity(pairs, k_c=K_C), repeats)[0],
    }


def make_lab_frame(width: int, height: int) -> Frame:
    """A frame of the MuJoCo lab (default scene) 0.35 m from the stem, at ``width`` x ``height``."""
    from harvest_qp.perception.synthetic import look_at
    from harvest_qp.sim import CameraConfig
    from harvest_qp.sim.lab_views import LabViews

    views = LabViews(None, camera=CameraConfig(downsample=848 // width))
    target = views.stem_middle
    pose = np.eye(4)
    pose[:3, 3] = target + 0.35 * np.array([-np.cos(0.3), np.sin(0.3), 0.2]) / np.linalg.norm(
        [np.cos(0.3), np.sin(0.3), 0.2]
    )
    pose[:3, :3] = look_at(pose[:3, 3], target)
    frame = views.render(pose)
    return Frame(frame.points, frame.stem_mask, frame.camera_position, views.robot.site_pose("gripper")[:3, 3])


def accuracy(n_seeds: int) -> dict[str, float]:
    """p_sb, l and p_gd against the lab's ground truth (the figures of the notes)."""
    from harvest_qp.perception.synthetic import view_poses
    from harvest_qp.sim.lab_views import LabViews

    rows = []
    for seed in [None, *range(1, n_seeds + 1)]:
        views = LabViews(seed)
        gripper = views.robot.site_pose("gripper")[:3, 3]
        rng = np.random.default_rng(0 if seed is None else seed)
        for pose in view_poses(views.stem_middle, rng, 12, distance=(0.3, 0.45)):
            frame = views.render(pose)
            stem_points, other = frame.points[frame.stem_mask], frame.points[~frame.stem_mask]
            if len(stem_points) < 10:
                continue
            row = {"seen": frame.base_seen, "coverage": frame.coverage}
            for name, kwargs in (
                ("new", {"camera_position": frame.camera_position, "non_stem_points": other}),
                ("paper_formula", {"camera_position": frame.camera_position, "base_estimator": "paper"}),
                ("former", {"max_spread_ratio": 0.5, "base_estimator": "paper"}),
            ):
                model = fit_stem(stem_points, gripper, **kwargs)
                row[name] = model
            model = row["new"]
            if model.valid:
                row["error"] = float(np.linalg.norm(model.base - frame.true_base))
                row["l_ratio"] = model.length / frame.true_free_length
                row["hidden"] = bool(model.quality.base_hidden)
                row["trusted"] = model.trusted()
                obstacles = classify.obstacles_near_stem_base(other, model.base, model.length)
                for mode, scene_points in (("selection", other), ("attr_point", None)):
                    free = compute_free_space(
                        obstacles, model.base, model.length, frame.camera_position, scene_points=scene_points
                    )
                    if free.valid:
                        row[f"gd_surface_{mode}"] = float(views.surface_distance(free.target)[0])
                        row[f"gd_wood_{mode}"] = views.segment_clearance(model.base, free.target, skip=0.005)
                        row[f"gd_behind_plane_{mode}"] = "behind the obstacle plane" in free.reason
                camera_side = ~free.behind_plane
                if camera_side.any():
                    row["best_wood"] = float(views.surface_distance(free.samples[camera_side], wood_only=True).max())
                    row["best_surface"] = float(views.surface_distance(free.samples[camera_side]).max())
            for name in ("paper_formula", "former"):
                other_model = row[name]
                row[f"error_{name}"] = (
                    float(np.linalg.norm(other_model.base - frame.true_base)) if other_model.valid else np.nan
                )
                row[f"valid_{name}"] = other_model.valid
            rows.append(row)

    def figure(values) -> np.ndarray:
        return np.array([v for v in values if v is not None and np.isfinite(v)], dtype=float)

    seen = [r for r in rows if r["seen"]]
    report: dict[str, float] = {"views_with_stem": len(rows), "views_seeing_base": len(seen)}
    errors = figure(r.get("error") for r in seen)
    report["accepted_seeing_base"] = float(np.mean([r["new"].valid for r in seen]))
    report["p_sb_median_mm"] = 1e3 * float(np.median(errors))
    report["p_sb_p95_mm"] = 1e3 * float(np.percentile(errors, 95))
    report["p_sb_max_mm"] = 1e3 * float(errors.max())
    for name in ("paper_formula", "former"):
        e = figure(r[f"error_{name}"] for r in seen)
        report[f"accepted_{name}"] = float(np.mean([r[f"valid_{name}"] for r in seen]))
        report[f"p_sb_median_mm_{name}"] = 1e3 * float(np.median(e))
        report[f"p_sb_p95_mm_{name}"] = 1e3 * float(np.percentile(e, 95))
    fitted = [r for r in rows if "error" in r]
    far = [r for r in fitted if r["error"] > 0.007]
    report["views_over_7mm"] = len(far)
    report["flagged_over_7mm"] = float(np.mean([r["hidden"] for r in far])) if far else float("nan")
    report["flagged_seeing_base"] = float(np.mean([r["hidden"] for r in fitted if r["seen"]]))
    trusted = [r for r in fitted if r["trusted"]]
    report["trusted_views"] = len(trusted)
    report["trusted_max_mm"] = 1e3 * max(r["error"] for r in trusted)
    covered = [r for r in fitted if r["coverage"] >= 0.9 and r["seen"]]
    ratio = figure(r["l_ratio"] for r in covered)
    report["l_views"] = len(covered)
    report["l_within_15pct"] = float(np.mean(np.abs(ratio - 1.0) <= 0.15))
    report["l_ratio_p5"], report["l_ratio_median"], report["l_ratio_p95"] = (
        float(x) for x in np.percentile(ratio, [5, 50, 95])
    )
    for mode in ("selection", "attr_point"):
        surface = figure(r.get(f"gd_surface_{mode}") for r in trusted)
        wood = figure(r.get(f"gd_wood_{mode}") for r in trusted)
        report[f"p_gd_{mode}_surface_min_mm"] = 1e3 * float(surface.min())
        report[f"p_gd_{mode}_surface_median_mm"] = 1e3 * float(np.median(surface))
        report[f"p_gd_{mode}_under_10mm"] = int(np.count_nonzero(surface < 0.01))
        report[f"p_gd_{mode}_stem_in_wood"] = int(np.count_nonzero(wood <= 0.0))
        report[f"p_gd_{mode}_stem_wood_min_mm"] = 1e3 * float(wood.min())
        report[f"p_gd_{mode}_behind_plane"] = sum(bool(r.get(f"gd_behind_plane_{mode}")) for r in trusted)
    best_wood = figure(r.get("best_wood") for r in trusted)
    report["best_camera_side_wood_min_mm"] = 1e3 * float(best_wood.min())
    report["best_camera_side_wood_median_mm"] = 1e3 * float(np.median(best_wood))
    return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in report.items()}


# ------------------------------------------------------------------ the brute-force version


@dataclass
class BruteForceResult:
    stem_base: np.ndarray
    target: np.ndarray
    n_pairs: int
    velocity: np.ndarray


def _skew_times(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.cross(a, b)


def bruteforce(frame: Frame, *, chunk_pairs: int = 1_000_000) -> BruteForceResult:
    # Classification with boolean masks.
    stem_points = frame.points[frame.stem_mask]
    non_stem = frame.points[~frame.stem_mask]
    stem = fit_stem(stem_points, frame.gripper, camera_position=frame.camera, non_stem_points=non_stem)
    base, length = stem.base, stem.length
    grasp_obstacles = non_stem[np.linalg.norm(non_stem - base, axis=1) < length]

    # Free space: exhaustive nearest-sample search for every projected obstacle.
    samples = base + length * fibonacci_sphere(N_SAMPLES)
    offsets = grasp_obstacles - base
    projected = base + length * offsets / np.linalg.norm(offsets, axis=1)[:, None]
    occupied = np.zeros(N_SAMPLES, dtype=bool)
    for start in range(0, len(projected), 2000):
        block = projected[start : start + 2000]
        distances = np.linalg.norm(block[:, None, :] - samples[None, :, :], axis=2)
        occupied[np.argmin(distances, axis=1)] = True
    centroid = grasp_obstacles.mean(axis=0)
    normal = np.linalg.svd(grasp_obstacles - centroid, full_matrices=False)[2][2]
    normal = normal if normal @ (frame.camera - centroid) > 0 else -normal
    free = samples[~occupied & ((samples - centroid) @ normal >= 0.0)]
    # eq:attr_point by brute force: all free samples against all projected obstacles.
    clearance = np.linalg.norm(free[:, None, :] - projected[None, :, :], axis=2).min(axis=1)
    target = free[int(np.argmax(clearance))]

    # Unveiling: eq:nearest over all n_S x n_O pairs, chunked by stem points.
    camera = frame.camera
    p_co = non_stem - camera
    stems_per_chunk = max(1, chunk_pairs // max(1, len(non_stem)))
    n_pairs = 0
    omega = np.zeros((len(stem_points), 3))
    for start in range(0, len(stem_points), stems_per_chunk):
        p_cs = stem_points[start : start + stems_per_chunk] - camera
        length_cs = np.linalg.norm(p_cs, axis=1)
        projection = (p_cs @ p_co.T) / length_cs[:, None]  # (p_cs / |p_cs|)^T p_co
        interior = (projection > 0.0) & (projection < length_cs[:, None])
        fraction = np.clip(projection / length_cs[:, None], 0.0, 1.0)
        nearest = camera + fraction[:, :, None] * p_cs[:, None, :]  # eq:nearest, all three branches
        gap = nearest - non_stem[None, :, :]
        distance = np.linalg.norm(gap, axis=2)
        r_hat = distance - D_O
        near = r_hat < D_A
        n_pairs += int(np.count_nonzero(near))
        # eq:u_ij, eq:omega_pivot on the interior pairs, eq:omega_i summed per stem point.
        j, k = np.nonzero(near & interior)
        r = np.maximum(r_hat[j, k], 1e-6)
        barrier = D_A**2 - (D_A - r) ** 2
        e = (D_A - r)[:, None] * gap[j, k] / distance[j, k][:, None]
        u = (2.0 / barrier * np.log(D_A**2 / barrier))[:, None] * e
        lever = nearest[j, k] - stem_points[start + j]
        pair_omega = _skew_times(lever, u) / (lever * lever).sum(axis=1)[:, None]
        np.add.at(omega, start + j, pair_omega)
    rays = stem_points - camera
    velocity = K_C * np.concatenate((_skew_times(rays, omega).sum(axis=0), omega.sum(axis=0)))  # eq:v_c2
    return BruteForceResult(base, target, n_pairs, velocity)


def check_agreement(fast, slow: BruteForceResult) -> None:
    np.testing.assert_allclose(fast.stem_base, slow.stem_base, atol=1e-12)
    np.testing.assert_allclose(fast.target, slow.target, atol=1e-12)
    assert len(fast.unveiling) == slow.n_pairs, (len(fast.unveiling), slow.n_pairs)
    np.testing.assert_allclose(unveiling_velocity(fast.unveiling, k_c=K_C), slow.velocity, rtol=1e-8)


# ------------------------------------------------------------------ optional scikit-learn


def sklearn_stand_ins(frame: Frame, repeats: int) -> dict[str, float] | None:
    """k-means and the p_gd nearest-neighbour query with scikit-learn, if importable."""
    try:
        from sklearn.cluster import KMeans
        from sklearn.neighbors import NearestNeighbors
    except ImportError:
        return None
    split = classify.split_scene(frame.points, frame.stem_mask)
    stem = fit_stem(split.stem, frame.gripper)
    obstacles = classify.obstacles_near_stem_base(split.non_stem, stem.base, stem.length)
    free_space = compute_free_space(obstacles, stem.base, stem.length, frame.camera)
    return {
        "sklearn KMeans(2)": median_ms(lambda: KMeans(2, n_init=1, random_state=0).fit(split.stem), repeats)[0],
        "scipy kmeans2 (ours)": median_ms(lambda: fit_stem(split.stem, frame.gripper), repeats)[0],
        "sklearn NearestNeighbors p_gd": median_ms(
            lambda: (
                NearestNeighbors(n_neighbors=1).fit(free_space.projected_obstacles).kneighbors(free_space.kept_samples)
            ),
            repeats,
        )[0],
    }


# ------------------------------------------------------------------ main


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30, help="timed calls per measurement (default 30)")
    parser.add_argument("--bruteforce-848", action="store_true", help="also time the brute force at 848x480 (minutes)")
    parser.add_argument(
        "--lab", action="store_true", help="also time the stages on lab frames (MuJoCo ray-cast camera)"
    )
    parser.add_argument("--accuracy", action="store_true", help="only the accuracy on lab views (no timing)")
    parser.add_argument("--seeds", type=int, default=40, help="sampled scenes for --accuracy (12 views each)")
    args = parser.parse_args()
    if args.accuracy:
        print(json.dumps(accuracy(args.seeds)))
        return

    print(f"BLAS threads: OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}; load average {os.getloadavg()}")
    report: dict[str, object] = {}
    for name, (width, height) in RESOLUTIONS.items():
        frame = make_frame(width, height)
        n_stem = int(np.count_nonzero(frame.stem_mask))
        fast_ms, fast = median_ms(lambda frame=frame: pipeline(frame), args.repeats)
        selection_ms, _ = median_ms(lambda frame=frame: pipeline(frame, "clearance"), args.repeats)
        print(
            f"\n== {name}: {len(frame.points)} points, {n_stem} stem points, {len(fast.unveiling)} ray/obstacle pairs"
        )
        print(
            f"   (candidate obstacles after the cull: {fast.unveiling.n_candidate_obstacles}, grasp obstacles: "
            f"{len(fast.grasp_obstacles)}, free samples: {int(fast.free_space.free.sum())})"
        )
        print(
            f"   pipeline (process_cloud) median {fast_ms:8.2f} ms   target <= {TARGET_MS[name]:.0f} ms: "
            f"{'met' if fast_ms <= TARGET_MS[name] else 'MISSED'}"
        )
        print(f"   pipeline with the p_gd selection (default) median {selection_ms:8.2f} ms")
        for stage, ms in pipeline_stages(frame, args.repeats).items():
            print(f"     {stage:<26} {ms:8.2f} ms")
        report[f"pipeline_ms_{name}"] = round(fast_ms, 3)
        report[f"pipeline_selection_ms_{name}"] = round(selection_ms, 3)
        report[f"n_points_{name}"] = len(frame.points)
        report[f"n_stem_{name}"] = n_stem
        report[f"n_pairs_{name}"] = len(fast.unveiling)
        report[f"target_met_{name}"] = fast_ms <= TARGET_MS[name]

        if name == "283x160" or args.bruteforce_848:
            brute_repeats = 3 if name == "283x160" else 1
            brute_ms, slow = median_ms(lambda frame=frame: bruteforce(frame), brute_repeats)
            check_agreement(fast, slow)
            print(
                f"   brute force      median {brute_ms:8.2f} ms   ({brute_ms / fast_ms:.0f}x slower; "
                "same p_sb, p_gd, pairs and V_cu)"
            )
            report[f"bruteforce_ms_{name}"] = round(brute_ms, 3)
            report[f"speedup_{name}"] = round(brute_ms / fast_ms, 1)
        else:
            print("   brute force      skipped (10^9 pairs; run with --bruteforce-848)")

        stand_ins = sklearn_stand_ins(frame, args.repeats)
        if stand_ins is None:
            print("   scikit-learn     not importable: skipped")
        else:
            for stage, ms in stand_ins.items():
                print(f"     {stage:<30} {ms:8.2f} ms")

    if args.lab:
        for name, (width, height) in RESOLUTIONS.items():
            frame = make_lab_frame(width, height)
            n_stem = int(np.count_nonzero(frame.stem_mask))
            lab_ms, _ = median_ms(lambda frame=frame: pipeline(frame, "clearance"), args.repeats)
            print(f"\n== lab {name}: {len(frame.points)} points, {n_stem} stem points")
            print(f"   pipeline (process_cloud, default) median {lab_ms:8.2f} ms")
            for stage, ms in pipeline_stages(frame, args.repeats).items():
                print(f"     {stage:<26} {ms:8.2f} ms")
            report[f"lab_pipeline_ms_{name}"] = round(lab_ms, 3)

    report["blas_threads"] = os.environ["OPENBLAS_NUM_THREADS"]
    print(json.dumps(report))


if __name__ == "__main__":
    main()
