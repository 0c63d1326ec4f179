"""Bundle adjustment alone on a BAL problem (e.g. the real Ladybug-49 in
../shared/realdata/bal/): our torch Levenberg–Marquardt + Schur adjuster on the CPU or a GPU,
or gtsam's (CPU), or the peers of ``bench/ba_peers.py`` (COLMAP's adjuster through pycolmap;
pyceres with a Python cost function), intrinsics held fixed, no robust loss.

Usage: python bench/ba.py BAL_FILE --solver ours|gtsam|pycolmap|pyceres [--device cpu|cuda]
                          [--json]
                          [--out ADJUSTED.txt] [--max-iterations 100]
       python bench/ba.py --synthetic CAMERAS [--points-per-camera 40] ...
(a street of CAMERAS cameras 1 m apart, each point seen from about 8 of them: the scaling
rows)

Cost = ½ Σ squared reprojection residuals in pixels under the BAL camera model, computed the
same way (numpy, float64) for every solver from the adjusted parameters. Observations whose
point lies behind its camera in the input are left out first (gtsam drops such factors; the
count is printed), so every solver adjusts the same problem. ``--out`` writes the adjusted
problem in BAL format so anyone can recompute the cost. Asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from cusfm_ros.core.mapping.bal_model import BalProblem
from cusfm_ros.io.bal_file import read_bal, write_bal


def adjust(problem: BalProblem, solver: str, device: str, max_iterations: int
           ) -> tuple[BalProblem, dict]:
    if solver in ("pycolmap", "pyceres"):
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        import ba_peers

        return getattr(ba_peers, f"{solver}_adjust")(problem, max_iterations)
    if solver == "gtsam":
        from cusfm_ros.core.mapping.bal_gtsam import GtsamBalAdjuster, GtsamBalOptions

        result = GtsamBalAdjuster(GtsamBalOptions(max_iterations=max_iterations)).solve(
            problem)
        return result.problem, {"seconds": result.seconds, "iterations": result.iterations}
    import torch

    from cusfm_ros.core.mapping.bal_model import BalProjection
    from cusfm_ros.core.mapping.schur_adjuster import SchurAdjuster, SchurAdjusterOptions

    options = SchurAdjusterOptions(max_iterations=max_iterations, device=device)
    model = BalProjection(problem.cameras, torch.device(device), torch.float64)
    adjuster = SchurAdjuster(options)
    if device.startswith("cuda"):  # first call pays CUDA's start-up: not the solver's time
        adjuster.solve(model, problem.cam_from_world_rotation, problem.cameras[:, 3:6],
                       problem.points3d_in_world, problem.obs_camera, problem.obs_point,
                       problem.obs_uv_px)
    result = adjuster.solve(model, problem.cam_from_world_rotation, problem.cameras[:, 3:6],
                            problem.points3d_in_world, problem.obs_camera, problem.obs_point,
                            problem.obs_uv_px)
    adjusted = problem.with_poses(result.cam_from_world_rotation,
                                  result.cam_from_world_translation, result.points3d_in_world)
    stats = {"seconds": result.seconds, "iterations": result.iterations}
    if device.startswith("cuda"):
        stats["peak_gpu_memory_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return adjusted, stats


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bal_file", nargs="?")
    parser.add_argument("--synthetic", type=int, default=None, metavar="CAMERAS")
    parser.add_argument("--points-per-camera", type=int, default=40)
    parser.add_argument("--solver", choices=("ours", "gtsam", "pycolmap", "pyceres"),
                        default="ours")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (ours only)")
    parser.add_argument("--max-iterations", type=int, default=100)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--out", default=None, help="write the adjusted problem (BAL)")
    args = parser.parse_args(argv)
    if args.solver != "ours" and args.device != "cpu":
        parser.error(f"{args.solver} runs on the CPU only here")
    if (args.bal_file is None) == (args.synthetic is None):
        parser.error("give a BAL_FILE or --synthetic CAMERAS")
    if args.synthetic is not None:
        from cusfm_ros.sim.bal_problem import street_bal_problem

        problem, _ = street_bal_problem(args.synthetic,
                                        args.points_per_camera * args.synthetic)
        name = f"synthetic street, {args.synthetic} cameras"
    else:
        problem, name = read_bal(args.bal_file), Path(args.bal_file).name
    kept = problem.in_front()
    dropped = len(problem.obs_camera) - len(kept.obs_camera)
    adjusted, stats = adjust(kept, args.solver, args.device, args.max_iterations)
    summary = {"solver": args.solver, "device": args.device, "problem": name,
               "cameras": len(kept.cameras), "points": len(kept.points3d_in_world),
               "observations": len(kept.obs_camera), "dropped_behind_camera": dropped,
               "initial_cost": kept.cost(), "final_cost": adjusted.cost(), **stats}
    if args.out:
        write_bal(adjusted, args.out)
    if args.json:
        print(json.dumps(summary))
    else:
        for key, value in summary.items():
            print(f"{key:24s} {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
