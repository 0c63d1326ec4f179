"""Extrinsic recalibration: the mapper with every camera's ``base_link_from_cam`` refined, and
a report per camera of the change and how well the data constrains it.

``ExtrinsicCalibration(options).solve(bag, run_dir)`` runs the mapper's stages up to
``export`` with ``mapping.optimize_extrinsics`` and ``bundle_adjustment.extrinsic_covariance``
on (``frame_type`` rig), then writes ``RUN_DIR/calibration.json``: per camera the input and
refined extrinsic, the change (mm, degrees), the 1-sigma per axis and the axes the data
cannot pin down (``core/calibration.py``), against base_link and, for every camera but the
first, against the first camera (``relative``). A camera whose pose in the rig (against the
first camera; the first camera: against base_link) has such axes is named under
``unconstrained_cameras``. The refined extrinsics are ``RUN_DIR/extrinsics.yaml`` (export)
and ``/tf_static`` in ``RUN_DIR/results.mcap``. Shared by ``cusfm calibrate`` and the
``extrinsic_calibration`` node.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np

from cusfm_ros.core.calibration import ExtrinsicChange, rig_changes
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.errors import CusfmError
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.extrinsics_yaml import read_extrinsics
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.pipeline.mapper import STAGE_NAMES, Mapper
from cusfm_ros.pipeline.stores import load_keyframes

logger = logging.getLogger(__name__)
CALIBRATION_STEPS = tuple(STAGE_NAMES[:STAGE_NAMES.index("export") + 1])


def calibration_options(options):
    """``options`` with extrinsic refinement and its covariance switched on."""
    from cusfm_ros.errors import ConfigError

    if options.frame_type != "rig":
        raise ConfigError("calibration refines the rig's extrinsics: use frame_type rig")
    if options.mapping.rolling_shutter_line_delay_s > 0:
        raise ConfigError("extrinsic calibration needs the global-shutter model (set "
                          "rolling_shutter_line_delay_s to 0)")
    return dataclasses.replace(
        options,
        mapping=dataclasses.replace(options.mapping, optimize_extrinsics=True),
        bundle_adjustment=dataclasses.replace(options.bundle_adjustment,
                                              extrinsic_covariance=True))


def _pose(pose: Rigid3) -> dict:
    return {"translation_m": pose.translation.tolist(), "quat_xyzw": pose.quat_xyzw().tolist()}


def _nan_to_none(values: np.ndarray) -> list:
    return [None if not np.isfinite(v) else float(v) for v in values]


def change_record(change: ExtrinsicChange) -> dict:
    return {"input": _pose(change.input_base_from_cam),
            "refined": _pose(change.refined_base_from_cam),
            "translation_change_mm": (change.translation_change_m * 1e3).tolist(),
            "translation_change_norm_mm": float(np.linalg.norm(change.translation_change_m)
                                                * 1e3),
            "rotation_change_deg": change.rotation_change_deg,
            "sigma_mm": _nan_to_none(change.sigma_m * 1e3),
            "sigma_deg": _nan_to_none(change.sigma_deg),
            "constrained": change.constrained, "weak_axes": list(change.weak_axes)}


class ExtrinsicCalibration:
    def __init__(self, options) -> None:
        self.options = calibration_options(options)

    def solve(self, bag, run_dir, overwrite: bool = False) -> dict:
        run = RunDir(run_dir)
        Mapper(self.options).solve(bag, run_dir, list(CALIBRATION_STEPS), overwrite)
        return self.report(run)

    def report(self, run: RunDir) -> dict:
        keyframes = load_keyframes(run)
        summary = json.loads(run.mapping_summary.read_text())
        stored = summary.get("extrinsic_covariance")
        if stored is None:
            raise CusfmError(f"{run.mapping_summary} has no extrinsic covariance: the mapping "
                             "stage ran without calibration; rerun `cusfm calibrate`")
        refined = read_extrinsics(run.extrinsics)
        ba = self.options.bundle_adjustment
        names = list(keyframes.rig.names)
        order = [stored["cameras"].index(n) for n in names]
        index = np.concatenate([np.arange(6 * k, 6 * k + 6) for k in order])
        joint = np.array(stored["matrix"], dtype=np.float64)[np.ix_(index, index)]
        absolute, relative = rig_changes(
            names, {c.name: c.rig_from_cam for c in keyframes.rig},
            {n: refined.cameras[n].rig_from_cam for n in names}, joint,
            ba.extrinsic_prior_sigma_m, ba.extrinsic_prior_sigma_deg)
        cameras, weak = {}, []
        for camera in keyframes.rig:
            change = absolute[camera.name]
            entry = {"frame_id": camera.frame_id, **change_record(change)}
            if camera.name in relative:
                entry["relative_to"] = names[0]
                entry["relative"] = change_record(relative[camera.name])
            cameras[camera.name] = entry
            pinned = relative.get(camera.name, change)
            if not pinned.constrained:
                weak.append(camera.name)
            logger.info("calibration: %s moved %.1f mm, %.3f deg; sigma %s mm, %s deg%s",
                        camera.name, entry["translation_change_norm_mm"],
                        change.rotation_change_deg, np.round(change.sigma_m * 1e3, 2).tolist(),
                        np.round(change.sigma_deg, 3).tolist(),
                        f"; against base_link not constrained: {', '.join(change.weak_axes)}"
                        if change.weak_axes else "")
        report = {"base_frame": keyframes.rig.base_frame_id, "reference_camera": names[0],
                  "cameras": cameras,
                  "unconstrained_cameras": weak,
                  "prior_sigma": {"translation_mm": ba.extrinsic_prior_sigma_m * 1e3,
                                  "rotation_deg": ba.extrinsic_prior_sigma_deg},
                  "observation_sigma_px": ba.observation_sigma_px,
                  "extrinsics": str(run.extrinsics), "results_bag": str(run.results_bag)}
        with atomic_write(calibration_report_path(run)) as handle:
            json.dump(report, handle, indent=2)
        return report


def calibration_report_path(run: RunDir) -> Path:
    return run.root / "calibration.json"
