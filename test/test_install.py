"""`pip install .` ships the whole package: the wheel, installed into a fresh venv, imports
every layer, runs `cusfm --help` and maps a tiny simulated bag end to end."""

import json
import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _tracked_copy(target: Path) -> Path:
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout.split()
    for name in files:
        source = ROOT / name
        if source.is_file():
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            (target / name).write_bytes(source.read_bytes())
    return target


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    if not (ROOT / ".git").exists():
        pytest.skip("needs the git checkout to list the package's files")
    source = _tracked_copy(tmp_path_factory.mktemp("src"))
    dist = tmp_path_factory.mktemp("dist")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps",
                    "--no-build-isolation", "--disable-pip-version-check", "-w", str(dist),
                    str(source)], check=True, capture_output=True, text=True)
    return next(dist.glob("cusfm_ros-*.whl"))


def test_wheel_holds_every_package_and_declares_its_dependencies(wheel):
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
        metadata = archive.read(next(n for n in names if n.endswith("METADATA"))).decode()
    packages = {str(p.parent.relative_to(ROOT)) for p in (ROOT / "cusfm_ros").rglob("*.py")}
    shipped = {os.path.dirname(n) for n in names if n.endswith(".py")}
    assert packages <= shipped, sorted(packages - shipped)
    requires = {line.split(":", 1)[1].strip().split(">")[0].split("=")[0].strip().lower()
                for line in metadata.splitlines() if line.startswith("Requires-Dist:")}
    assert {"numpy", "scipy", "opencv-python-headless", "onnxruntime", "gtsam", "rosbags",
            "pyyaml", "h5py", "scikit-learn", "scikit-image"} <= requires, requires
    assert any(n.endswith("config/av.yaml") for n in names)  # presets ship as data


def test_fresh_venv_from_the_wheel_runs_cusfm(wheel, tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    python = venv / "bin" / "python"
    subprocess.run([str(python), "-m", "pip", "install", "--quiet", "--no-deps",
                    "--disable-pip-version-check", str(wheel)], check=True)
    # dependencies come from this environment's site-packages (a plain path entry: its .pth
    # files, among them our own editable install, are not processed)
    site = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig."
                           "get_paths()['purelib'])"], capture_output=True, text=True,
                          check=True).stdout.strip()
    Path(site, "zz_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    run = lambda *args: subprocess.run(list(args), cwd=tmp_path, env=env,  # noqa: E731
                                       capture_output=True, text=True, timeout=600)
    probe = run(str(python), "-c", "import cusfm_ros, cusfm_ros.pipeline.mapper, "
                "cusfm_ros.core.mapping, cusfm_ros.io.run_dir, cusfm_ros.ros.entry; "
                "from cusfm_ros.pipeline.options import preset_path; "
                "print(cusfm_ros.__file__); print(preset_path('av.yaml'))")
    assert probe.returncode == 0, probe.stderr
    module, preset = probe.stdout.split()
    assert module.startswith(str(venv)) and preset.startswith(str(venv)), probe.stdout
    cusfm = str(venv / "bin" / "cusfm")
    helped = run(cusfm, "--help")
    assert helped.returncode == 0 and "map" in helped.stdout, helped.stderr
    simulated = run(cusfm, "simulate", "sim", "--scene", "indoor", "--rig", "stereo",
                    "--frames", "12", "--image-size", "320x240")
    assert simulated.returncode == 0, simulated.stderr
    mapped = run(cusfm, "map", "sim/bag", "--out", "run", "--features", "sift",
                 "--max-keypoints", "600", "--min-translation-m", "0.2", "--skip-vocabulary",
                 "--skip-loops", "--skip-pose_graph")
    assert mapped.returncode == 0, mapped.stderr[-3000:]
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert report["summary"]["points"] > 100 and (tmp_path / "run" / "poses.tum").is_file()
