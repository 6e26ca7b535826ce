"""A synthetic scene in the BOP layout, beside its bag (``mireg synth ... --bop DIR``).

Object ids are the catalogue's order (``OBJECTS`` then ``UNTEXTURED_OBJECTS``, from 1), so
scenes exported into one folder share their models: ``models/obj_NNNNNN.ply`` is the object's
mesh in mm, its frame the ground truth's, with the pictures the scene shows on it
(``objects.textured_object_mesh``: a texture beside the PLY, as BOP's textured meshes come),
so that a model built from it has keypoints as one built from a real textured mesh does. Symmetries in
models_info.json: found from the mesh for the untextured objects; none for the textured ones
(their print tells every pose apart, and BOP's symmetries are those of the appearance).
Each frame: rgb/ and depth/ PNGs (depth the bag's 16UC1 mm, depth_scale 1), cam_K, the
ground-truth poses with the frame's visible fractions and visible boxes. Image id = frame index
(unique even where a scene drops frames or loops; BopDataset stamps image i at i / 30 s, so the
stamps are the bag's only for a 30 Hz scene without dropped frames or loops).
"""
from __future__ import annotations

from pathlib import Path

from ..datasets.bop import BopWriter, gt_info_from_mask
from .objects import OBJECTS, UNTEXTURED_OBJECTS, get_object, object_mesh, textured_object_mesh

MAX_SCENE_ID = 999_999      # scene folders are six digits


def catalogue_obj_id(name: str) -> int:
    """The BOP object id of a catalogue object (1-based, catalogue order)."""
    get_object(name)       # InputError for an unknown name
    return (list(OBJECTS) + list(UNTEXTURED_OBJECTS)).index(name) + 1


class SceneBopExport:
    """Writes the frames of one ``SyntheticScene`` as BOP scene ``scene_id`` under ``root``."""

    def __init__(self, root, scene, scene_id: int, split: str = "test"):
        from ..errors import InputError

        if not 0 <= int(scene_id) <= MAX_SCENE_ID:
            raise InputError(f"BOP scene id must be 0 to {MAX_SCENE_ID}, got {scene_id}")
        self.writer = BopWriter(Path(root), split)
        self.scene_writer = self.writer.scene(int(scene_id))      # refuses a scene written before, at once
        self.specs = (scene.target,) + tuple(scene.more_targets)
        self.obj_ids = [catalogue_obj_id(n) for n in scene.instance_objects]
        self.labels = [p.label for p in scene.instances]

    def add(self, frame) -> None:
        """One ``RenderedFrame``."""
        info = [gt_info_from_mask(frame.instance_mask == label, frame.depth_mm, v)
                for label, v in zip(self.labels, frame.visibility)]
        self.scene_writer.add_image(frame.index, frame.rgb, frame.depth_mm, frame.K,
                                    list(zip(self.obj_ids, frame.poses)), info)

    def close(self) -> None:
        """The scene's JSON files and the objects' models (written last: nothing is left
        behind by a run that failed before its frames)."""
        from ..models.mesh_model import mesh_symmetries

        self.scene_writer.close()
        for spec in self.specs:
            if spec.name in UNTEXTURED_OBJECTS:
                mesh = object_mesh(spec)
                self.writer.add_model(catalogue_obj_id(spec.name), mesh, mesh_symmetries(mesh))
            else:
                self.writer.add_model(catalogue_obj_id(spec.name), textured_object_mesh(spec), None)
