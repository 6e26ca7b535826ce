"""Several objects in one pass: every instance of each of several stored models. No ROS.

    reg = MultiModelRegistration([load_model("snack_box.npz"), load_model("can.npz")], PipelineConfig())
    result = reg.register_frame(rgb, depth_m, intrinsics)
    for inst in result.instances:       # by object (in the order of the models), then by id
        inst.object, inst.id, inst.T

What is shared and what is not:
- SIFT runs once per frame (``InstanceRegistration.detect``: search region, keypoints,
  lifting); it depends on the frame, not on the model.
- Matching (``frontend.multi_model_index``): ``joint``, the default with several SIFT
  models, searches one FLANN index over all models' descriptors once a frame and applies
  the ratio test within each model (``matching.JointMatcher``); ``per_model`` searches each
  model's own index exactly as with that model alone (three searches cost 2.8 x one). A
  keypoint may match several models; which object a region is, is decided by the selection
  below.
- ECC, recovery and selection run per model on that model's correspondences
  (``InstanceRegistration.solve``).
- Across models, one region of the image is one object: the instances of all models, by
  inlier count, each dropped when more than ``frontend.max_overlap`` of its box lies in a
  stronger instance's box of another model, or the other way round.

Models found by shape (``frontend.correspondences`` shape/both, from a mesh) run their own
pipeline per model (their shape matching is on depth) and join the selection; those with
both paths take the frame's one SIFT detection for their SIFT half (models with both paths
only: it runs beside the first one's shape path). With one model, the result is exactly
``InstanceRegistration``'s.
"""
from __future__ import annotations

import time

import numpy as np

from ..errors import InputError
from ..messages import CameraIntrinsics
from ..frontends.sift.matching import JointMatcher, prepare_descriptors
from ..models.model import ObjectModel
from ..threads import run_beside
from .pipeline import STAGES, FrameResult, Instance, InstanceRegistration, PipelineConfig, box_grid, check_frame


def check_model_names(models: list[ObjectModel], sources: list[str] | None = None) -> None:
    """InputError when two models share a name (their outputs could not be told apart)."""
    seen: dict[str, int] = {}
    for k, model in enumerate(models):
        if model.name in seen:
            where = "" if sources is None else f" ({sources[seen[model.name]]} and {sources[k]})"
            raise InputError(f"two models are named '{model.name}'{where}; every object needs its own name: "
                             f"rebuild one with `mireg build-model ... --name OTHER_NAME`")
        seen[model.name] = k


def load_models(paths) -> list[ObjectModel]:
    """Every model file in ``paths``, checked (InputError naming the bad file, or the two
    files whose models share a name)."""
    from ..models.model import load_model

    paths = [str(p) for p in paths]
    models = [load_model(p) for p in paths]
    check_model_names(models, paths)
    return models


class MultiModelRegistration:
    """Finds every instance of several stored objects in RGB-D frames, SIFT once per frame."""

    def __init__(self, models: list[ObjectModel], config: PipelineConfig | None = None,
                 sources: list[str] | None = None):
        models = list(models)
        if not models:
            raise InputError("no object model given")
        check_model_names(models, sources)
        self.models = models
        self.pipelines = [InstanceRegistration(m, config) for m in models]
        self.config = self.pipelines[0].config
        self._sift = [k for k, p in enumerate(self.pipelines) if p.correspondences == "sift"]
        # One SIFT detection a frame for every model that matches SIFT (``both`` too), made by
        # the first: one search region for them all, in which none may lose its objects' tops.
        self._detecting = [k for k, p in enumerate(self.pipelines) if p.correspondences in ("sift", "both")]
        if self._detecting:
            self.pipelines[self._detecting[0]].object_reach = max(self.pipelines[k].object_reach
                                                                  for k in self._detecting)
        self._grids = [box_grid(m.extent) + np.asarray(m.box_centre, np.float64) for m in models]
        fe = self.config.frontend
        self._joint = None
        if len(self._sift) > 1 and fe.matcher == "flann" and fe.multi_model_index == "joint":
            self._joint = JointMatcher([prepare_descriptors(models[k].descriptors, fe.root_sift) for k in self._sift],
                                       [models[k].keypoints_xyz for k in self._sift], fe.ratio, fe.ratio_separation,
                                       flann_checks=fe.joint_flann_checks)

    @property
    def names(self) -> list[str]:
        return [m.name for m in self.models]

    def warm_up(self) -> None:
        """Compile the kernels before the first frame (shared by every model): the first
        model's, and the shape path's on the first model that has shape data."""
        self.pipelines[0].warm_up()
        shaped = [p for p in self.pipelines if p.correspondences != "sift"]
        if shaped and shaped[0] is not self.pipelines[0]:
            shaped[0].warm_up()

    def register_frame(self, rgb: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics,
                       gravity: np.ndarray | None = None, only=None) -> FrameResult:
        """Every instance of every model in one frame; see the module's docstring. ``gravity``:
        see ``InstanceRegistration.register_frame``. ``only``: the indices of the models to
        look for in this frame (the objects known to be in it); None: all."""
        check_frame(rgb, depth_m, intrinsics)
        t = {s: 0.0 for s in STAGES}
        t0 = time.perf_counter()
        wanted = set(range(len(self.models)) if only is None else only)
        per_model: dict[int, FrameResult] = {k: FrameResult.empty({}) for k in range(len(self.models))
                                             if k not in wanted}
        sift = [k for k in self._sift if k in wanted]
        detecting = [k for k in self._detecting if k in wanted]
        n_kp = 0
        keypoints = None
        if sift:
            keypoints = self.pipelines[self._detecting[0]].detect(rgb, depth_m, intrinsics, t)
            n_kp = keypoints.detected
            # One joint search; or every model's own search queued at once, each model's ECC
            # and selection running as soon as its matches are in while the pool searches the
            # next models' (the search releases the GIL). "matching" is the time spent waiting.
            t1 = time.perf_counter()
            if self._joint is not None:
                joint = self._joint.match_later(keypoints.descriptors)()
                pending = {k: (lambda m=m: m[:2]) for k, m in zip(self._sift, joint) if k in wanted}
            else:
                pending = {k: self.pipelines[k].match_later(keypoints) for k in sift}
            t["matching"] += (time.perf_counter() - t1) * 1e3
            for k in sift:
                t1 = time.perf_counter()
                matches = pending[k]()
                t["matching"] += (time.perf_counter() - t1) * 1e3
                per_model[k] = self.pipelines[k].solve(keypoints, *matches)
        elif len(detecting) > 1:
            # Only models with both paths: the detection runs beside the first one's shape
            # path, as its own would (the beside thread takes it before that model's matching).
            first = self.pipelines[self._detecting[0]]        # the one whose search region fits all
            keypoints = run_beside(lambda: first.detect(rgb, depth_m, intrinsics, t))
        for k, pipeline in enumerate(self.pipelines):
            if k not in per_model:
                per_model[k] = pipeline.register_frame(rgb, depth_m, intrinsics, gravity,
                                                       keypoints if k in detecting else None)
                n_kp = max(n_kp, per_model[k].num_keypoints)
        for k, res in per_model.items():
            for stage, ms in res.timings_ms.items():
                if stage != "total" and (k not in self._sift or stage in ("ecc", "refinement")):
                    t[stage] = t.get(stage, 0.0) + ms
        t2 = time.perf_counter()
        result = self._select([per_model[k] for k in range(len(self.models))], n_kp)
        result.deadline_cut = any(res.deadline_cut for res in per_model.values())
        t["refinement"] += (time.perf_counter() - t2) * 1e3
        t["total"] = (time.perf_counter() - t0) * 1e3
        result.timings_ms = t
        return result

    def _select(self, results: list[FrameResult], n_kp: int) -> FrameResult:
        """One object per region: the instances of all models by inliers; each is dropped when
        it shares more than ``max_overlap`` of a box with a stronger one of another model.
        Survivors keep their order within their object and are renumbered there."""
        max_overlap = self.config.frontend.max_overlap
        pool = [(k, inst) for k, res in enumerate(results) for inst in res.instances]
        kept: list[tuple[int, Instance]] = []
        if len(results) > 1:
            # Boxes whose bounding spheres are apart share nothing: most pairs, skipped cheaply.
            centre = {id(inst): inst.T[:3, :3] @ np.asarray(self.models[k].box_centre, np.float64) + inst.T[:3, 3]
                      for k, inst in pool}
            radius = [float(np.linalg.norm(m.extent)) / 2.0 for m in self.models]

            def apart(k1, inst1, k2, inst2) -> bool:
                return float(np.linalg.norm(centre[id(inst1)] - centre[id(inst2)])) > radius[k1] + radius[k2]

            for k, inst in sorted(pool, key=lambda c: -c[1].inliers):
                if all(k2 == k or apart(k, inst, k2, inst2) or
                       (self._inside(k2, inst2, k, inst) <= max_overlap and
                        self._inside(k, inst, k2, inst2) <= max_overlap) for k2, inst2 in kept):
                    kept.append((k, inst))
        else:
            kept = pool
        instances, labels, uv, src, tgt = [], [], [], [], []
        for k, res in enumerate(results):
            mine = sorted((inst for k2, inst in kept if k2 == k), key=lambda i: i.id)
            new_label = np.full(len(res.instances) + 1, -1, np.int64)    # old id -> position in the output, -1
            for inst in mine:
                new_label[inst.id] = len(instances)
                instances.append(Instance(len([i for i in instances if i.object == inst.object]), inst.T,
                                          inst.inliers, inst.score, inst.object))
            labels.append(new_label[np.where(res.labels >= 0, res.labels, len(res.instances))])
            uv.append(res.keypoints_uv)
            src.append(res.model_xyz)
            tgt.append(res.scene_xyz)
        return FrameResult(instances, {}, np.concatenate(uv).astype(np.float32), np.concatenate(src).astype(np.float32),
                           np.concatenate(tgt).astype(np.float32), np.concatenate(labels), n_kp)

    def _inside(self, k_box: int, box: Instance, k_pts: int, pts: Instance) -> float:
        """Share of instance ``pts``'s box (its model's grid) inside instance ``box``'s box."""
        grid = self._grids[k_pts] @ pts.T[:3, :3].T + pts.T[:3, 3]           # camera frame
        local = (grid - box.T[:3, 3]) @ box.T[:3, :3]                        # box's model frame
        model = self.models[k_box]
        inside = np.abs(local - np.asarray(model.box_centre, np.float64)) <= np.asarray(model.extent) / 2.0
        return float(np.mean(inside.all(axis=1)))


__all__ = ["MultiModelRegistration", "check_model_names", "load_models"]
