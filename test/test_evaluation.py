import json

import numpy as np
import pytest

from cusfm_ros.cli.main import main
from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error, associate
from cusfm_ros.core.geometry import Rigid3, se3_exp
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import ConfigError, EvaluationError
from cusfm_ros.io.tum import write_tum

from conftest import make_loop_trajectory


def drifted_estimate(reference: Trajectory, rng, scale=1.0) -> Trajectory:
    """Noisy, drifting, re-stamped, partly missing copy of ``reference`` in another frame."""
    keep = np.sort(rng.choice(len(reference), size=len(reference) - 23, replace=False))
    stamps = reference.stamps_ns[keep] + rng.integers(-6_000_000, 6_000_000, size=len(keep))
    stamps[5] += 40_000_000  # beyond max_diff: must not be associated
    order = np.argsort(stamps)
    stamps, keep = stamps[order], keep[order]
    poses = reference.world_from_body[keep].copy()
    drift = se3_exp(np.outer(np.arange(len(keep)) / len(keep), [0, 0, 0.05, 0.3, -0.2, 0.1]))
    poses = poses @ drift
    poses[:, :3, 3] += rng.normal(scale=0.05, size=(len(keep), 3))
    other_frame = Rigid3.from_rotvec([0.1, -0.3, 1.2], [10, -4, 2]).matrix()
    poses = other_frame @ poses
    poses[:, :3, 3] *= scale
    return Trajectory(stamps, poses)


def evo_statistics(ref_path, est_path, sim3: bool, max_diff: float):
    evo = pytest.importorskip("evo")  # noqa: F841
    from evo.core import metrics, sync
    from evo.tools import file_interface
    traj_ref = file_interface.read_tum_trajectory_file(str(ref_path))
    traj_est = file_interface.read_tum_trajectory_file(str(est_path))
    traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est, max_diff=max_diff)
    traj_est.align(traj_ref, correct_scale=sim3)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    stats = ape.get_all_statistics()
    stats["n"] = traj_ref.num_poses
    return stats


@pytest.mark.parametrize("align, scale", [("se3", 1.0), ("sim3", 0.37)])
@pytest.mark.parametrize("swap", [False, True], ids=["est_shorter", "ref_shorter"])
def test_matches_evo_ape(tmp_path, rng, capsys, align, scale, swap):
    reference = make_loop_trajectory(300)
    estimate = drifted_estimate(reference, rng, scale)
    ref_path, est_path = tmp_path / "gt.tum", tmp_path / "est.tum"
    write_tum(ref_path, estimate if swap else reference)
    write_tum(est_path, reference if swap else estimate)
    expected = evo_statistics(ref_path, est_path, align == "sim3", 0.01)
    assert main(["evaluate", str(ref_path), str(est_path), "--align", align, "--json"]) == 0
    ours = json.loads(capsys.readouterr().out)
    assert set(ours) == {"rmse", "mean", "median", "std", "min", "max", "n"}
    assert ours["n"] == expected["n"] < len(estimate)
    for key in ("rmse", "mean", "median", "std", "min", "max"):
        assert ours[key] == pytest.approx(expected[key], abs=1e-6), key
    assert ours["rmse"] > 0.01  # the drift is really there


def test_perfect_estimate_in_another_frame_has_zero_error(loop_trajectory):
    frame = Rigid3.from_rotvec([0.3, 0.2, 0.1], [5, 6, 7]).matrix()
    moved = Trajectory(loop_trajectory.stamps_ns, frame @ loop_trajectory.world_from_body)
    result = absolute_trajectory_error(loop_trajectory, moved)
    assert result.rmse < 1e-9 and result.n == len(loop_trajectory)
    unaligned = absolute_trajectory_error(loop_trajectory, moved, AteOptions(align="none"))
    assert unaligned.rmse > 1.0


def test_association_prefers_nearest_and_earlier_on_ties():
    ref = np.array([0, 100, 200, 300])
    est = np.array([49, 150, 251, 1000])
    ref_idx, est_idx = associate(ref, est, 60e-9)
    # 150 ties between 100 and 200: the earlier wins; 1000 is too far from anything
    assert ref_idx.tolist() == [0, 1, 3] and est_idx.tolist() == [0, 1, 2]


def test_cli_text_output(tmp_path, capsys, loop_trajectory):
    write_tum(tmp_path / "a.tum", loop_trajectory)
    assert main(["evaluate", str(tmp_path / "a.tum"), str(tmp_path / "a.tum")]) == 0
    out = capsys.readouterr().out
    assert "ATE (se3 alignment, 200 associated poses)" in out
    assert "rmse   0.000000 m" in out


def test_cli_errors_are_one_line_and_exit_1(tmp_path, capsys, loop_trajectory):
    write_tum(tmp_path / "a.tum", loop_trajectory)
    shifted = Trajectory(loop_trajectory.stamps_ns + 5_000_000_000_000,
                         loop_trajectory.world_from_body)
    write_tum(tmp_path / "b.tum", shifted)
    assert main(["evaluate", str(tmp_path / "a.tum"), str(tmp_path / "b.tum")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("cusfm evaluate: error: no stamps of the two trajectories lie within")
    assert "--max-diff" in err and len(err.splitlines()) == 1
    (tmp_path / "bad.tum").write_text("1.0 0 0 0 0 0 0\n")
    assert main(["evaluate", str(tmp_path / "a.tum"), str(tmp_path / "bad.tum")]) == 1
    assert "bad.tum:line 1: expected 8 fields" in capsys.readouterr().err


def test_bad_options():
    with pytest.raises(ConfigError, match="unknown alignment 'umeyama'"):
        AteOptions(align="umeyama")
    with pytest.raises(EvaluationError, match="at least 3"):
        t = make_loop_trajectory(2)
        absolute_trajectory_error(t, t)
