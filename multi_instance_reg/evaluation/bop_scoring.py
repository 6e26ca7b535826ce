"""Scoring a BOP results file as the BOP challenge scores the ViVo task (6D localisation of a
varying number of instances of a varying number of objects; bop.felk.cvut.cz, BOP 2019-2022
methodology; Hodan et al. ECCVW 2020), plus the project's own MHR / MHP / MHF1.

Steps, per target (scene, image, object, inst_count) of ``test_targets_bop19.json`` (or, when
the dataset has none, one per object with ground truth in each image, inst_count = its
instances at least 10 % visible, as BOP makes its targets):
1. the ``inst_count`` estimates of that object in that image with the highest score are kept
   (ties in file order);
2. their errors against each ground-truth instance of the object that counts are computed:
   VSD for each tau, MSSD, MSPD (``pose_errors``). What counts: with a targets file, the
   ``inst_count`` most visible instances (the BOP toolkit's rule; BOP's targets files count
   the instances at least 10 % visible, so these are they); without one, the instances at
   least 10 % visible;
3. for each error function and threshold, estimates are matched greedily in order of
   decreasing score, each to the unmatched counted instance with the smallest error below
   the threshold;
4. recall = matched instances / counted instances over all targets; AR_X = the mean recall
   over X's thresholds (VSD: every (tau, theta) pair); AR = the mean of AR_VSD, AR_MSSD and
   AR_MSPD. Per object the same over that object's targets.

MHR / MHP / MHF1 (NOTES.md section 2) at 10 deg / 2 cm over the object's symmetries, on every
estimate of the file in the target images (not only the top ones: precision counts them
all), instances under 10 % visible neither credit nor blame (``tools.offline.match_frame``),
averaged over images.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .pose_errors import (distance_factor, mspd_placed, mssd_placed, place, symmetric_poses, symmetry_transforms,
                          vertex_order, vsd)
from .render import render_depth


def _steps(first: float, count: int = 10) -> tuple[float, ...]:
    return tuple(round(first * (k + 1), 6) for k in range(count))


@dataclass(frozen=True)
class ScoreSettings:
    """BOP 2019-2022's settings (eval_bop19 of the BOP toolkit, its documented parameters)."""
    vsd_delta_m: float = 0.015                      # visibility tolerance delta (15 mm; ITODD 5 mm)
    vsd_taus: tuple = _steps(0.05)                  # misalignment tolerance, fractions of the diameter
    vsd_thetas: tuple = _steps(0.05)                # correctness threshold on e_VSD
    mssd_thresholds: tuple = _steps(0.05)           # fractions of the diameter
    mspd_thresholds: tuple = _steps(5.0)            # pixels x r, r = image width / 640
    min_visib_fract: float = 0.1                    # less visible instances are not counted
    max_symmetry_step: float = 0.01                 # continuous symmetries: vertex step / diameter
    mh_max_rre_deg: float = 10.0                    # the project's MHF1 hit: rotation ...
    mh_max_rte_m: float = 0.02                      # ... and translation bounds


@dataclass
class EvalModel:
    """An object as scoring needs it (metres, model frame)."""
    obj_id: int
    diameter_m: float
    vertices: np.ndarray            # (V, 3) every mesh vertex (MSPD)
    triangles: np.ndarray           # (F, 3) (VSD's renders)
    hull: np.ndarray                # (H, 3) convex hull vertices (MSSD's maximum is on them)
    syms: np.ndarray                # (S, 4, 4) BOP's symmetry transforms, the identity first
    symmetries: object = None       # symmetry.Symmetries for the MHF1 matching (None: none)
    hull_order: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))   # vertex_order(hull)
    order: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))        # vertex_order(vertices)


def load_eval_model(dataset, obj_id: int, max_symmetry_step: float = 0.01) -> EvalModel:
    """The dataset's mesh of ``obj_id`` (models_eval/obj_NNNNNN.ply when the dataset has it,
    else models/; mm) and its models_info entry."""
    from scipy.spatial import ConvexHull
    from scipy.spatial import QhullError

    from ..datasets.bop import model_file_name
    from ..meshes import load_mesh

    info = dataset.models_info.get(int(obj_id))
    if info is None:
        raise InputError(f"object {obj_id} is not in {dataset.root / 'models' / 'models_info.json'}: "
                         f"scoring needs its diameter and symmetries")
    # BOP datasets ship models_eval/ (vertices resampled evenly) for computing pose errors;
    # the display models in models/ when there are none.
    path = dataset.root / "models_eval" / model_file_name(obj_id)
    mesh = load_mesh(path if path.is_file() else dataset.model_path(obj_id), "mm")
    used = mesh.vertices[np.unique(mesh.triangles)]
    try:
        hull = used[ConvexHull(used).vertices]
    except QhullError:                          # flat or degenerate: every vertex counts
        hull = used
    return EvalModel(int(obj_id), info.diameter_mm / 1000.0, used, mesh.triangles, hull,
                     symmetry_transforms(info, max_symmetry_step), info.symmetries(),
                     vertex_order(hull), vertex_order(used))


@dataclass
class TargetErrors:
    """One target's estimates (score order) against its object's ground-truth instances."""
    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int
    counted: np.ndarray             # (G,) bool: the instance counts (visible enough)
    vsd: np.ndarray                 # (E, G, taus) errors; inf where not computed
    mssd: np.ndarray                # (E, G) metres
    mspd: np.ndarray                # (E, G) pixels
    diameter_m: float
    mspd_unit_px: float             # r = image width / 640


def greedy_matches(errors: np.ndarray, counted: np.ndarray, threshold: float) -> int:
    """BOP's matching: estimates (rows, in order of decreasing score) each take the unmatched
    counted instance (column) with the smallest error below ``threshold``; the number matched."""
    free = np.asarray(counted, bool).copy()
    matched = 0
    for row in np.asarray(errors, np.float64).reshape(-1, len(free)):
        ok = free & (row < threshold)
        if ok.any():
            free[np.flatnonzero(ok)[np.argmin(row[ok])]] = False
            matched += 1
    return matched


def derived_targets(dataset, min_visib_fract: float) -> list:
    """Targets as BOP makes them when the dataset has no targets file: per image with ground
    truth, per object, inst_count = its instances at least ``min_visib_fract`` visible."""
    from ..datasets.bop import BopTarget

    out = []
    for s in dataset.scene_ids:
        scene = dataset.scene(s)
        if scene.gt is None:
            continue
        for im in scene.image_ids:
            entries = scene.gt.get(im, [])
            vis = None if scene.visib_fract is None else scene.visib_fract.get(im)
            counts: dict[int, int] = {}
            for k, (obj, _) in enumerate(entries):
                if vis is None or vis[k] >= min_visib_fract:
                    counts[obj] = counts.get(obj, 0) + 1
            out += [BopTarget(s, im, obj, n) for obj, n in sorted(counts.items())]
    return out


class BopScorer:
    """Scores results against one dataset split; models are loaded once and kept."""

    def __init__(self, dataset, settings: ScoreSettings | None = None):
        self.dataset = dataset
        self.settings = settings or ScoreSettings()
        self.models: dict[int, EvalModel] = {}
        # Where scoring spends its time (seconds, summed over images): what a user waits for.
        self.seconds = {"read": 0.0, "render": 0.0, "vsd": 0.0, "mssd": 0.0, "mspd": 0.0, "mh": 0.0, "models": 0.0}

    def model(self, obj_id: int) -> EvalModel:
        if obj_id not in self.models:
            t = time.perf_counter()
            self.models[obj_id] = load_eval_model(self.dataset, obj_id, self.settings.max_symmetry_step)
            self.seconds["models"] += time.perf_counter() - t
        return self.models[obj_id]

    # ----------------------------------------------------------------------- errors

    def image_errors(self, frame, targets: list, estimates: list, most_visible: bool = True) -> list[TargetErrors]:
        """Errors of one image's targets. ``frame``: the image (``BopDataset.read_frame``);
        ``estimates``: its BopEstimate rows. Which instances count: ``most_visible``, the
        target's ``inst_count`` most visible ones (the BOP toolkit's rule with a targets
        file, whose inst_count BOP made by counting the instances at least 10 % visible: the
        same instances); else those at least ``min_visib_fract`` visible."""
        st = self.settings
        scene_id, im_id = frame.scene_id, frame.im_id
        scene = self.dataset.scene(scene_id)
        K = frame.intrinsics.K
        W, H = frame.intrinsics.width, frame.intrinsics.height
        factor = distance_factor(K, W, H)
        dist_test = np.where(np.isfinite(frame.depth_m), frame.depth_m, 0).astype(np.float32) * factor
        entries = scene.gt.get(im_id, [])
        vis = None if scene.visib_fract is None else scene.visib_fract.get(im_id)
        out = []
        for target in targets:
            model = self.model(target.obj_id)
            gt_index = [k for k, (obj, _) in enumerate(entries) if obj == target.obj_id]
            seen = [1.0 if vis is None else float(vis[k]) for k in gt_index]
            if most_visible:
                counted = np.zeros(len(gt_index), bool)
                # Stable: equally visible instances in ground-truth order.
                counted[sorted(range(len(seen)), key=lambda g: -seen[g])[:max(0, target.inst_count)]] = True
            else:
                counted = np.array([v >= st.min_visib_fract for v in seen], bool)
            mine = [e for e in estimates if e.obj_id == target.obj_id]
            # Highest scores first; Python's sort is stable, so ties keep the file's order.
            top = sorted(mine, key=lambda e: -e.score)[:max(0, target.inst_count)]
            E, G = len(top), len(gt_index)
            errs_vsd = np.full((E, G, len(st.vsd_taus)), np.inf)
            errs_mssd = np.full((E, G), np.inf)
            errs_mspd = np.full((E, G), np.inf)
            r = W / 640.0
            if E and counted.any():
                T_gt = [entries[k][1] for k in gt_index]
                clock = time.perf_counter()
                renders_gt = {g: render_depth(model.vertices, model.triangles, T_gt[g], K, W, H)
                              for g in range(G) if counted[g]}
                self.seconds["render"] += time.perf_counter() - clock
                true_poses = {g: symmetric_poses(T_gt[g], model.syms) for g in renders_gt}
                mssd_cap = max(st.mssd_thresholds) * model.diameter_m
                mspd_cap = max(st.mspd_thresholds) * r
                for e, est in enumerate(top):
                    T_est = est.T_m
                    clock = time.perf_counter()
                    render_est = render_depth(model.vertices, model.triangles, T_est, K, W, H)
                    hull_est, all_est = place(T_est, model.hull), place(T_est, model.vertices)
                    self.seconds["render"] += time.perf_counter() - clock
                    for g in renders_gt:
                        t0 = time.perf_counter()
                        errs_vsd[e, g] = vsd(render_est, renders_gt[g], dist_test, factor, st.vsd_delta_m,
                                             st.vsd_taus, model.diameter_m)
                        t1 = time.perf_counter()
                        errs_mssd[e, g] = mssd_placed(hull_est, true_poses[g], model.hull, model.hull_order, mssd_cap)
                        t2 = time.perf_counter()
                        errs_mspd[e, g] = mspd_placed(all_est, true_poses[g], K, model.vertices, model.order, mspd_cap)
                        t3 = time.perf_counter()
                        self.seconds["vsd"] += t1 - t0
                        self.seconds["mssd"] += t2 - t1
                        self.seconds["mspd"] += t3 - t2
            out.append(TargetErrors(scene_id, im_id, target.obj_id, target.inst_count, counted, errs_vsd, errs_mssd,
                                    errs_mspd, model.diameter_m, r))
        return out

    # ----------------------------------------------------------------------- recall

    def recalls(self, errors: list[TargetErrors]) -> dict:
        """Recall per threshold and AR per error function over ``errors``' targets."""
        st = self.settings
        total = int(sum(t.counted.sum() for t in errors))

        def recall(err_of, th_of):
            if total == 0:
                return 0.0
            return sum(greedy_matches(err_of(t), t.counted, th_of(t)) for t in errors) / total

        vsd_r = [[recall(lambda t, i=i: t.vsd[:, :, i], lambda t, th=th: th) for th in st.vsd_thetas]
                 for i in range(len(st.vsd_taus))]
        mssd_r = [recall(lambda t: t.mssd, lambda t, f=f: f * t.diameter_m) for f in st.mssd_thresholds]
        mspd_r = [recall(lambda t: t.mspd, lambda t, k=k: k * t.mspd_unit_px) for k in st.mspd_thresholds]
        ar = {"AR_VSD": float(np.mean(vsd_r)), "AR_MSSD": float(np.mean(mssd_r)), "AR_MSPD": float(np.mean(mspd_r))}
        return {"AR": float(np.mean(list(ar.values()))), **ar, "instances": total,
                "recall_vsd": vsd_r, "recall_mssd": mssd_r, "recall_mspd": mspd_r}

    # ----------------------------------------------------------------------- everything

    def score(self, estimates: list, progress=None) -> dict:
        """The whole report (a JSON-ready dict) for a results file's rows ``estimates``."""
        from ..datasets.rgbd_bag import SkipCounter
        from ..metrics import combine_scores, summarize
        from ..tools.offline import match_frame

        st = self.settings
        t0 = time.perf_counter()
        targets = self.dataset.targets
        targets_from = "test_targets file"
        if targets is None:
            targets, targets_from = derived_targets(self.dataset, st.min_visib_fract), "ground truth (no targets file)"
            if not targets:
                raise InputError(f"{self.dataset.split_dir} has no ground truth (scene_gt.json) with an instance at least "
                                 f"{st.min_visib_fract:g} visible, and the dataset no test_targets_bop19.json: "
                                 f"nothing to score against")
        by_image: dict[tuple[int, int], list] = {}
        for t in targets:
            by_image.setdefault((t.scene_id, t.im_id), []).append(t)
        rows: dict[tuple[int, int], list] = {}
        for e in estimates:
            rows.setdefault((e.scene_id, e.im_id), []).append(e)
        ignored = sum(len(v) for k, v in rows.items() if k not in by_image)

        # What stops a run is found before the first image: a scene without ground truth, an
        # object without mesh or models_info entry. A bad image is skipped and counted.
        for s in sorted({k[0] for k in by_image}):
            if self.dataset.scene(s).gt is None:
                raise InputError(f"{self.dataset.scene(s).directory} has no scene_gt.json: scoring needs ground truth")
        for obj in sorted({t.obj_id for t in targets}):
            self.model(obj)
        skipped = SkipCounter()
        errors: list[TargetErrors] = []
        image_seconds = []
        mh_images, mh_objects = [], {}
        for n, (key, image_targets) in enumerate(sorted(by_image.items())):
            t_img = time.perf_counter()
            try:
                frame = self.dataset.read_frame(*key)
            except InputError as exc:
                skipped.add(str(exc))
                continue
            self.seconds["read"] += time.perf_counter() - t_img
            errors += self.image_errors(frame, image_targets, rows.get(key, []), targets_from == "test_targets file")
            t_mh = time.perf_counter()
            # The project's MHF1 on every estimate of the image, object by object.
            scene = self.dataset.scene(key[0])
            entries = scene.gt.get(key[1], [])
            vis = None if scene.visib_fract is None else scene.visib_fract.get(key[1])
            per_obj = []
            for obj in sorted({o for o, _ in entries} | {e.obj_id for e in rows.get(key, [])}):
                gi = [k for k, (o, _) in enumerate(entries) if o == obj]
                T_gt = np.array([entries[k][1] for k in gi]).reshape(-1, 4, 4)
                T_est = np.array([e.T_m for e in rows.get(key, []) if e.obj_id == obj]).reshape(-1, 4, 4)
                broken = ~np.isfinite(T_est).all(axis=(1, 2))       # NaN in a row: an estimate that hits nothing
                info = self.dataset.models_info.get(obj)
                sym = None if info is None else info.symmetries()
                v = None if vis is None else np.asarray(vis)[gi]
                s, _ = match_frame(T_gt, T_est[~broken], v, st.min_visib_fract, st.mh_max_rre_deg, st.mh_max_rte_m,
                                   sym)
                s.n_est += int(broken.sum())
                per_obj.append(s)
                mh_objects.setdefault(obj, []).append(s)
            mh_images.append(combine_scores(per_obj))
            self.seconds["mh"] += time.perf_counter() - t_mh
            image_seconds.append(time.perf_counter() - t_img)
            if progress is not None:
                progress(n + 1, len(by_image))

        report = {"dataset": self.dataset.name, "split": self.dataset.split, "targets_from": targets_from,
                  **self.recalls(errors)}
        per_object = {}
        for obj in sorted({t.obj_id for t in errors}):
            r = self.recalls([t for t in errors if t.obj_id == obj])
            mh = summarize(mh_objects.get(obj, []))
            per_object[str(obj)] = {k: r[k] for k in ("AR", "AR_VSD", "AR_MSSD", "AR_MSPD", "instances")} | {
                "MHR": mh["MHR"], "MHP": mh["MHP"], "MHF1": mh["MHF1"]}
        mh = summarize(mh_images)
        times = {}
        for e in estimates:
            times.setdefault((e.scene_id, e.im_id), e.time_s)
        report.update({
            "MHR": mh["MHR"], "MHP": mh["MHP"], "MHF1": mh["MHF1"], "MF": mh["MF"],
            "mh_hits": mh["hits"], "mh_instances": mh["gt"], "mh_estimates": mh["est"],
            "per_object": per_object,
            "images": len(by_image) - skipped.count, "targets": len(errors),
            "estimates_in_file": len(estimates), "estimates_evaluated": int(sum(len(t.mssd) for t in errors)),
            "estimates_outside_targets": ignored,
            "estimates_not_finite": int(sum(not np.all(np.isfinite(e.T_m)) for e in estimates)),
            "images_skipped": skipped.count, "skip_reasons": skipped.reasons,
            # BOP's time: the mean of the images' times when every row gives one, else -1.
            "average_time_per_image_s": float(np.mean(list(times.values())))
            if times and min(times.values()) >= 0 else -1.0,
            "scoring_seconds": time.perf_counter() - t0,
            "scoring_seconds_by_step": dict(self.seconds),
            "scoring_seconds_per_image_median": float(np.median(image_seconds)) if image_seconds else None,
            "settings": {"vsd_delta_mm": st.vsd_delta_m * 1000.0, "vsd_taus": list(st.vsd_taus),
                         "vsd_thetas": list(st.vsd_thetas), "mssd_thresholds": list(st.mssd_thresholds),
                         "mspd_thresholds_px_per_r": list(st.mspd_thresholds), "min_visib_fract": st.min_visib_fract,
                         "max_symmetry_step": st.max_symmetry_step, "mh_max_rre_deg": st.mh_max_rre_deg,
                         "mh_max_rte_m": st.mh_max_rte_m},
        })
        return report


def score_results(dataset, estimates: list, settings: ScoreSettings | None = None, progress=None) -> dict:
    """Score ``estimates`` (``datasets.bop.BopEstimate`` rows) against ``dataset``
    (``datasets.bop.BopDataset``): see the module's docstring and ``BopScorer.score``."""
    return BopScorer(dataset, settings).score(estimates, progress)


__all__ = ["ScoreSettings", "BopScorer", "score_results", "greedy_matches", "derived_targets", "load_eval_model",
           "EvalModel", "TargetErrors"]
