"""The stage contract: resume semantics of the generic runner, killed stages, option precedence
(preset < command line, booleans both ways, CLI == node), and stages on explicit inputs."""

import json
import sys

import numpy as np
import pytest

from cusfm_ros.cli.main import build_parser, main
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.sim.generator import SimulationOptions, Simulator

# SIFT + k-NN: no ONNX models needed, seconds per stage on two cores
FAST = ["--min-translation-m", "0.3", "--features", "sift", "--max-keypoints", "768",
        "--set", "vocabulary.depth=3"]


@pytest.fixture(scope="module")
def loop_bag(tmp_path_factory):
    """An indoor stereo loop driven twice: the loops stage finds loops."""
    return Simulator(SimulationOptions(
        scene="indoor", rig="stereo", frames=60, loops=2, image_width=320, image_height=240,
        odom_yaw_drift_deg_per_m=0.3, odom_scale_error=0.02, seed=3)
    ).generate(tmp_path_factory.mktemp("loop") / "sim")


def _written(run):
    """Every stage output file with its modification time (not the runner's bookkeeping:
    the stage records, report.json and the page drawn from it)."""
    return {p: p.stat().st_mtime_ns for p in run.rglob("*") if p.is_file()
            and p.name not in ("report.json", "report.html", "COMPLETE")
            and "stages" not in p.relative_to(run).parts}


def _records(run):
    return {p.stem: json.loads(p.read_text()) for p in (run / "stages").glob("*.json")
            if p.stem != "digests"}


def _stages(run):
    return json.loads((run / "report.json").read_text())["stages"]


def test_resume_reruns_exactly_what_changed(loop_bag, tmp_path):
    run = tmp_path / "run"
    args = ["map", str(loop_bag / "bag"), "--out", str(run)] + FAST
    assert main(args) == 0
    first = _stages(run)
    assert first["loops"]["loops"] > 0 and not any(e["reused"] for e in first.values())
    # refined poses carry the keyframes' full nanosecond stamps (frames_meta keeps only µs)
    from cusfm_ros.io.tum import read_tum
    refined, initial = read_tum(run / "poses.tum"), read_tum(run / "initial_poses.tum")
    assert np.array_equal(refined.stamps_ns, initial.stamps_ns)
    assert np.any(refined.stamps_ns % 1000 != 0)
    # the same command twice: every stage reused, no output rewritten
    written = _written(run)
    assert main(args) == 0
    assert all(e["reused"] for e in _stages(run).values())
    assert _written(run) == written
    before = _records(run)
    # a vocabulary option: vocabulary and loops rerun, features untouched
    assert main(args + ["--set", "vocabulary.branching=8"]) == 0
    after, stages = _records(run), _stages(run)
    assert not stages["vocabulary"]["reused"] and not stages["loops"]["reused"]
    assert stages["keyframes"]["reused"] and stages["features"]["reused"]
    features = RunDir(run).features
    assert features.stat().st_mtime_ns == written[features]
    assert after["vocabulary"]["options"]["vocabulary"]["branching"] == 8
    # loops.json changed (other BoW scores), so the pose graph reran; downstream of it a
    # stage reran exactly when the content of one of its inputs changed
    assert after["loops"]["outputs"]["loops"] != before["loops"]["outputs"]["loops"]
    assert not stages["pose_graph"]["reused"]
    for name in ("pairs", "matching", "mapping", "export"):
        changed = after[name]["inputs"] != before[name]["inputs"]
        assert stages[name]["reused"] is not changed, name
    # the report keeps each stage's own options; the vocabulary's record shows today's
    assert stages["vocabulary"]["options"]["vocabulary"]["branching"] == 8
    assert stages["features"]["fingerprint"] == before["features"]["fingerprint"]


def test_a_killed_stage_is_redone_and_reaches_the_same_result(loop_bag, tmp_path,
                                                              monkeypatch):
    from cusfm_ros.pipeline.stages import matching

    reference = tmp_path / "reference"
    bag = str(loop_bag / "bag")
    assert main(["map", bag, "--out", str(reference)] + FAST) == 0
    # kill the matching stage after 40 pairs (KeyboardInterrupt stands in for a signal), on
    # one thread: on two, the 41st call may belong to an earlier pair than the 40th, and then
    # fewer than 40 complete entries precede the failure (seen in CI: 39)
    run = tmp_path / "run"
    calls = {"n": 0}
    real = matching.essential_inliers

    def dying(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 40:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(matching, "essential_inliers", dying)
    assert main(["map", bag, "--out", str(run), "--cpu-threads", "1"] + FAST) == 130  # Ctrl-C
    monkeypatch.setattr(matching, "essential_inliers", real)
    assert json.loads((run / "stages" / "matching.json").read_text())["status"] == "running"
    assert not (run / "mapping").exists() and not (run / "poses.tum").exists()
    # resumed: the complete entries are kept, the rest is redone
    assert main(["map", bag, "--out", str(run)] + FAST) == 0
    stages = _stages(run)
    assert not stages["matching"]["reused"]
    assert stages["matching"]["matched_now"] == stages["matching"]["pairs"] - 40
    assert stages["features"]["reused"] and stages["pairs"]["reused"]
    assert (run / "poses.tum").read_bytes() == (reference / "poses.tum").read_bytes()
    # killed again, this time leaving a truncated HDF5 store: detected and redone whole
    record = run / "stages" / "matching.json"
    data = json.loads(record.read_text())
    record.write_text(json.dumps({**data, "status": "running"}))
    store = RunDir(run).verified_matches
    store.write_bytes(store.read_bytes()[:96])
    assert main(["map", bag, "--out", str(run)] + FAST) == 0
    assert _stages(run)["matching"]["matched_now"] == stages["matching"]["pairs"]
    assert (run / "poses.tum").read_bytes() == (reference / "poses.tum").read_bytes()


def test_stage_selection_errors(loop_bag, tmp_path, capsys):
    run = str(tmp_path / "run")
    assert main(["map", str(loop_bag / "bag"), "--out", run, "--steps", "mapping",
                 "--skip-mapping"]) == 1
    assert "no stage left to run" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
    assert main(["map", str(loop_bag / "bag"), "--out", run, "--steps", "features"]) == 1
    err = capsys.readouterr().err
    assert "run/keyframes is missing: run the keyframes stage first" in err, err


def _cli_options(argv):
    from cusfm_ros.cli.options import resolved_options

    return resolved_options(build_parser().parse_args(argv))


def test_option_precedence_booleans_and_cli_equals_node(tmp_path):
    from cusfm_ros.ros.parameters import mapper_request, mapper_specs

    def mapper_options_from_parameters(given):
        values = {spec.name: spec.default for spec in mapper_specs()}
        values.update({"bag": "bag", "out": "run", **given})
        return mapper_request(values).options

    preset = tmp_path / "preset.yaml"
    preset.write_text("frame_type: rig\nexport: {rgb: true, colmap_binary: true}\n"
                      "features: {extractor: {aliked: {max_keypoints: 300}}}\n"
                      "loops: {top_k: 7}\n")
    base = ["map", "bag", "--out", "run", "--config", str(preset)]
    options = _cli_options(base)
    assert options.export.rgb and options.export.colmap_binary  # the preset's values kept
    assert options.features.extractor.aliked.max_keypoints == 300 and options.loops.top_k == 7
    switched = _cli_options(base + ["--no-rgb", "--max-keypoints", "500", "--frame-type",
                                    "camera", "--set", "loops.top_k=9", "--seed", "4"])
    assert not switched.export.rgb and switched.export.colmap_binary  # CLI beats the preset
    assert switched.features.extractor.aliked.max_keypoints == 500
    assert switched.frame_type == "camera" and switched.loops.top_k == 9 and switched.seed == 4
    off = tmp_path / "off.yaml"
    off.write_text("export: {rgb: false}\n")
    assert _cli_options(["map", "b", "--out", "r", "--config", str(off), "--rgb"]).export.rgb
    # the ROS node resolves the same options from the same inputs
    node = mapper_options_from_parameters({
        "config": str(preset), "rgb": False, "max_keypoints": 500, "frame_type": "camera",
        "seed": 4, "bag": "bag", "out": "run", "steps": ["keyframes"]})
    assert node == _cli_options(base + ["--no-rgb", "--max-keypoints", "500",
                                        "--frame-type", "camera", "--seed", "4"])
    assert mapper_options_from_parameters({"config": str(preset)}) == options


@pytest.mark.parametrize("preset, message", [
    ("loops: {seed: 3}\n", "preset.yaml: loops.seed: set `seed` once at the top level"),
    ("features: {extractor: {aliked: {device: cuda}}}\n",
     "features.extractor.aliked.device: set `device` once at the top level"),
    ("pose_graph: {frame_type: camera}\n", "pose_graph.frame_type: set `frame_type` once"),
    ("loops: {top_k: many}\n", "preset.yaml: loops.top_k: expected an integer, got 'many'"),
    ("mapping: {max_pose_change_m: .inf}\n", "mapping.max_pose_change_m: must be finite"),
    ("loops: 3\n", "preset.yaml: loops: expected a mapping of options, got 3"),
    ("features: {extractor: {name: orb}}\n", "unknown extractor 'orb'"),
    ("bogus: {}\n", "unknown section(s) ['bogus']"),
])
def test_bad_presets_name_the_file_and_key(tmp_path, preset, message):
    from cusfm_ros.errors import ConfigError
    from cusfm_ros.pipeline.options import resolve_options

    path = tmp_path / "preset.yaml"
    path.write_text(preset)
    with pytest.raises(ConfigError) as error:
        resolve_options(path)
    assert message in str(error.value)


def test_every_feature_component_knob_is_reachable_from_yaml(tmp_path):
    from cusfm_ros.pipeline.options import resolve_options

    options = resolve_options({"features": {
        "extractor": {"name": "sift", "sift": {"contrast_threshold": 0.04, "root_sift": False}},
        "matcher": {"knn": {"ratio": 0.7, "metric": "cosine", "mutual": False}}}})
    assert options.features.extractor.sift.contrast_threshold == 0.04
    assert options.features.matcher.name == "knn"  # SIFT picks k-NN when none is named
    knn = options.features.matcher.knn
    assert knn.metric == "cosine" and not knn.mutual and knn.ratio == 0.7
    lightglue = resolve_options(None, {"features.matcher.lightglue.filter_threshold": 0.3,
                                       "features.extractor.aliked.nms_radius": 3})
    assert lightglue.features.matcher.lightglue.filter_threshold == 0.3
    assert lightglue.features.extractor.aliked.nms_radius == 3


def test_stages_run_on_explicit_inputs(loop_bag, tmp_path):
    """Feature extraction and pair matching on an image list and a pair list of our choosing,
    outside any run directory (what a localizer does with query images)."""
    from cusfm_ros.core.features.sift import SiftExtractor, SiftOptions
    from cusfm_ros.core.features.knn import KnnMatcher
    from cusfm_ros.io.feature_store import FeatureStore
    from cusfm_ros.pipeline.stages.features import extract_features
    from cusfm_ros.pipeline.stages.keyframes import KeyframeOptions, extract_keyframes
    from cusfm_ros.pipeline.stages.matching import MatchingOptions, match_pairs

    keyframes = extract_keyframes(loop_bag / "bag", tmp_path / "kf", KeyframeOptions(
        min_translation_m=0.5)).keyframe_set
    frames = keyframes.images_in_time_order()[:6]
    images = [(k.image_name, tmp_path / "kf" / k.image_name) for k in frames]
    with FeatureStore(tmp_path / "query.h5", {"mine": 1}) as store, \
            FeatureStore(tmp_path / "verified.h5", {"mine": 1}) as verified:
        counts = extract_features(images, SiftExtractor(SiftOptions(max_keypoints=500)), store)
        assert counts["extracted"] == 6
        assert sorted(store.feature_names()) == sorted(n for n, _ in images)
        pairs = [(frames[i].image_name, frames[i + 1].image_name) for i in range(5)]
        cameras = {k.image_name: keyframes.rig[k.camera_name].camera for k in frames}
        result = match_pairs(pairs, cameras, store, KnnMatcher(), MatchingOptions(), 0,
                             verified)
        assert result["pairs"] == 5 and result["verified_matches"] > 100
        assert all(verified.has_matches(a, b) for a, b in pairs)


def test_map_stage_stores_the_loops_stage_bows(loop_bag, tmp_path, monkeypatch):
    """The map stage takes each keyframe's bag of words from loops/bows.npz (else from
    vocabulary/bows.npz) instead of quantizing again: the same map, byte for byte; rows of
    another vocabulary are not used, and a damaged file is named."""
    from cusfm_ros.core.retrieval.database import ImageDatabase
    from cusfm_ros.errors import FormatError
    from cusfm_ros.io.bow_file import read_bows
    from cusfm_ros.io.vocabulary_file import load_vocabulary
    from cusfm_ros.pipeline.stages.vocabulary import build_vocabulary
    from cusfm_ros.pipeline.stores import load_keyframes

    run = RunDir(tmp_path / "run")
    args = ["map", str(loop_bag / "bag"), "--out", str(run.root), *FAST]
    assert main(args) == 0
    vocabulary = load_vocabulary(run.vocabulary)
    rows = read_bows(run.loop_bows, vocabulary)
    keyframes = load_keyframes(run)
    assert sorted(rows) == sorted(k.image_name for k in keyframes.keyframes)
    stored = {p.name: p.read_bytes() for p in run.map_dir.iterdir()}
    quantized, bows = [], ImageDatabase.bows
    monkeypatch.setattr(ImageDatabase, "bows", lambda self, documents: bows(
        self, [quantized.append(d) or d for d in documents]))
    assert main(args + ["--steps", "map", "--overwrite"]) == 0
    assert quantized == []  # every row came from the loops stage
    run.loop_bows.unlink()  # loops skipped: the vocabulary stage's rows
    assert main(args + ["--steps", "map"]) == 0
    assert quantized == []
    assert {p.name: p.read_bytes() for p in run.map_dir.iterdir()} == stored
    run.vocabulary_bows.unlink()
    assert main(args + ["--steps", "map"]) == 0
    assert len(quantized) == len(keyframes.keyframes)
    assert {p.name: p.read_bytes() for p in run.map_dir.iterdir()} == stored
    other, _ = build_vocabulary(_descriptors(run, keyframes)[:10],
                                _sift_options().vocabulary, seed=1)
    assert main(args + ["--steps", "loops"]) == 0
    assert read_bows(run.loop_bows, other) == {}
    run.loop_bows.write_bytes(b"not an npz")
    with pytest.raises(FormatError, match=r"bows.npz: not a bag-of-words file .*rerun the loops"):
        read_bows(run.loop_bows, vocabulary)


def test_loops_stage_takes_the_vocabulary_stages_bows(loop_bag, tmp_path, monkeypatch):
    """The vocabulary stage writes every image's bag of words (known from its IDF weights);
    the loops stage builds its database from them instead of quantizing again: the same
    loops and rows byte for byte; without the file it quantizes every keyframe."""
    from cusfm_ros.core.retrieval.vocabulary import VocabularyTree
    from cusfm_ros.errors import FormatError
    from cusfm_ros.io.bow_file import read_bows
    from cusfm_ros.io.vocabulary_file import load_vocabulary
    from cusfm_ros.pipeline.stores import load_keyframes

    run = RunDir(tmp_path / "run")
    args = ["map", str(loop_bag / "bag"), "--out", str(run.root), *FAST]
    assert main(args + ["--steps", "keyframes", "features", "vocabulary", "loops"]) == 0
    vocabulary = load_vocabulary(run.vocabulary)
    keyframes = load_keyframes(run)
    assert sorted(read_bows(run.vocabulary_bows, vocabulary)) == sorted(
        k.image_name for k in keyframes.keyframes)
    stored = {p: p.read_bytes() for p in (run.loops, run.loop_bows)}
    assert json.loads(run.loops.read_text())["loops"]  # the fixture closes its loop
    descended, quantize = [], VocabularyTree.quantize
    monkeypatch.setattr(VocabularyTree, "quantize", lambda self, d, chunk=None: (
        descended.append(len(d)), quantize(self, d, chunk))[1])
    assert main(args + ["--steps", "loops", "--overwrite"]) == 0
    assert descended == []  # every row from vocabulary/bows.npz
    assert {p: p.read_bytes() for p in stored} == stored
    run.vocabulary_bows.unlink()
    assert main(args + ["--steps", "loops", "--overwrite"]) == 0
    assert sum(descended) == sum(len(f) for f in _descriptors(run, keyframes))
    assert {p: p.read_bytes() for p in stored} == stored
    run.vocabulary_bows.parent.mkdir(exist_ok=True)
    run.vocabulary_bows.write_bytes(b"not an npz")
    with pytest.raises(FormatError, match=r"bows.npz: not a bag-of-words file .*rerun the "
                                          r"vocabulary stage"):
        read_bows(run.vocabulary_bows, vocabulary)


def _sift_options():
    """The options of a run made with FAST."""
    from cusfm_ros.pipeline.options import resolve_options

    return resolve_options(None, {"features.extractor.name": "sift",
                                  "features.extractor.sift.max_keypoints": 768})


def _descriptors(run, keyframes):
    from cusfm_ros.pipeline.stores import open_features

    with open_features(run, _sift_options()) as store:
        return [store.features(k.image_name).descriptors for k in keyframes.keyframes]


def test_two_view_estimation_leaves_opencv_global_rng_alone(rng):
    import cv2

    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.core.relpose.two_view import TwoViewOptions, estimate_two_view

    points = rng.uniform(-1, 1, (300, 3)) + [0, 0, 6]
    motion = Rigid3.from_rotvec([0.02, 0.1, 0.0], [0.4, 0.0, 0.1])
    x0 = points[:, :2] / points[:, 2:]
    moved = points @ motion.rotation.T + motion.translation
    x1 = moved[:, :2] / moved[:, 2:]
    x1[:60] += rng.normal(0, 0.05, (60, 2))  # 20 % outliers
    cv2.setRNGSeed(99)
    expected = cv2.randu(np.zeros(4), 0, 1).copy()
    cv2.setRNGSeed(99)
    result = estimate_two_view(x0, x1, TwoViewOptions(threshold=1e-3, seed=5))
    assert np.array_equal(cv2.randu(np.zeros(4), 0, 1), expected)  # no side effect
    again = estimate_two_view(x0, x1, TwoViewOptions(threshold=1e-3, seed=5))
    assert np.array_equal(result.inlier_mask, again.inlier_mask)  # seeded: repeatable
    assert result.success and result.inlier_mask[60:].all() and result.num_inliers <= 245
    assert np.allclose(result.rotation, motion.rotation, atol=1e-3)
    direction = motion.translation / np.linalg.norm(motion.translation)
    assert np.allclose(result.translation_direction, direction, atol=1e-3)


def test_core_calls_no_global_rng_seeding():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "cusfm_ros"
    offenders = [str(p) for p in root.rglob("*.py")
                 if "cv2.setRNGSeed(" in p.read_text() or "np.random.seed(" in p.read_text()]
    assert not offenders


def test_stage_modules_spell_no_run_directory_paths():
    """Stages ask RunDir for every path (no `run_dir / "..."` literals)."""
    import re
    from pathlib import Path

    stages = Path(__file__).resolve().parents[1] / "cusfm_ros" / "pipeline" / "stages"
    pattern = re.compile(r"""(run_dir|root|run)\s*/\s*["']""")
    offenders = [p.name for p in stages.glob("*.py") if pattern.search(p.read_text())]
    assert not offenders


def test_registry_drives_options_steps_and_cli():
    from cusfm_ros.pipeline.options import SECTIONS, MapperOptions
    from cusfm_ros.pipeline.registry import STAGE_NAMES, STAGES

    assert STAGE_NAMES == ("keyframes", "features", "vocabulary", "loops", "pose_graph",
                           "pairs", "matching", "mapping", "export", "map")
    owned = {name for stage in STAGES for name in stage.sections}
    assert owned == set(SECTIONS)
    fields = {f for f in MapperOptions.__dataclass_fields__}
    assert fields == owned | {"seed", "device", "frame_type", "cpu_threads"}
    help_text = build_parser().parse_args(["map", "b", "--out", "o"])
    assert all(hasattr(help_text, f"skip_{name}") for name in STAGE_NAMES)
    # every declared input is some stage's output
    outputs = {a for stage in STAGES
               for a in stage.outputs + stage.optional_outputs + stage.provides}
    for stage in STAGES:
        assert set(stage.inputs + stage.optional_inputs) <= outputs, stage.name


def test_keyframes_record_keeps_nanoseconds(tmp_path):
    from cusfm_ros.core.cameras import PinholeCamera
    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.core.keyframes import Keyframe, KeyframeSet
    from cusfm_ros.core.rig import Rig, RigCamera
    from cusfm_ros.io.keyframes_file import read_keyframes, write_keyframes

    camera = PinholeCamera(640, 480, fx=500.0, fy=501.0, cx=320.5, cy=240.25)
    rig = Rig((RigCamera("left", camera, Rigid3.from_rotvec([0, 0.1, 0], [0.1, 0, 0])),))
    keyframes = KeyframeSet(rig, [Keyframe("0", "left", 1_700_000_000_123_456_789, "left/a.png",
                                           "s0", Rigid3.from_rotvec([0.1, 0.2, 0.3],
                                                                    [1.0, 2.0, 3.0]))])
    write_keyframes(tmp_path / "keyframes.json", keyframes)
    again = read_keyframes(tmp_path / "keyframes.json")
    assert again.keyframes[0].stamp_ns == 1_700_000_000_123_456_789
    assert again.keyframes[0].world_from_cam.is_close(keyframes.keyframes[0].world_from_cam,
                                                      1e-12, 1e-12)
    assert again.rig["left"].camera == camera and again.rig.base_frame_id == "base_link"


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))


@pytest.mark.parametrize("reader, stage", [("keyframes", "keyframes"), ("loops", "loops")])
@pytest.mark.parametrize("content, problem", [
    (None, "no such file (run the {stage} stage)"),
    ("{not json", "invalid JSON"),
    ('{"format": "other/9"}', "format: expected 'cusfm_{stage}/1'"),
])
def test_artifact_readers_name_the_file_and_the_fix(tmp_path, reader, stage, content, problem):
    from cusfm_ros.errors import FormatError
    from cusfm_ros.io.keyframes_file import read_keyframes
    from cusfm_ros.io.loops_file import read_loops

    path = tmp_path / f"{stage}.json"
    if content is not None:
        path.write_text(content)
    read = {"keyframes": read_keyframes, "loops": read_loops}[reader]
    with pytest.raises(FormatError) as error:
        read(path)
    assert str(error.value).startswith(str(path))
    assert problem.format(stage=stage) in str(error.value)


def test_fingerprints_read_only_the_chosen_component():
    from cusfm_ros.pipeline.options import resolve_options
    from cusfm_ros.pipeline.runner import option_value

    base = resolve_options(None, {"features.extractor.name": "sift"})
    other_aliked = resolve_options(None, {"features.extractor.name": "sift",
                                          "features.extractor.aliked.max_keypoints": 99})
    other_sift = resolve_options(None, {"features.extractor.name": "sift",
                                        "features.extractor.sift.max_keypoints": 99})
    path = "features.extractor"
    assert option_value(base, path) == option_value(other_aliked, path)
    assert option_value(base, path) != option_value(other_sift, path)


class _BatchedKnn:
    """k-NN behind a batched interface (``batch_pairs``, ``match_many``), recording the
    batches; matching one pair at a time is an error."""

    batch_pairs = 3

    def __init__(self) -> None:
        from cusfm_ros.core.features.knn import KnnMatcher

        self.knn, self.batches = KnnMatcher(), []

    def match(self, features0, features1):
        raise AssertionError("a batched matcher was asked for one pair")

    def match_many(self, pairs):
        self.batches.append(len(pairs))
        return [self.knn.match(*pair) for pair in pairs]


def test_batched_matches_keep_one_batch_in_flight():
    """``with_batched_matches`` launches the next batch before it hands out the items of the
    last (a GPU matches while the stage reads and pads the next pairs), in the items' order,
    each with its own matches; items with nothing to match pass through in place."""
    from cusfm_ros.pipeline.components import with_batched_matches

    events = []

    class Submitting:
        batch_pairs = 2

        def submit_many(self, pairs):
            batch = len([e for e in events if e[0] == "submit"])
            events.append(("submit", batch))

            def collect():
                events.append(("collect", batch))
                return [f"m{a}" for a, _ in pairs]
            return collect

    items = [(i, None if i % 3 == 0 else (i, i)) for i in range(10)]  # 6 pairs to match
    out = list(with_batched_matches(iter(items), Submitting(), lambda item: item[1],
                                    lambda item, found: (item[0], found)))
    assert [i for i, _ in out] == list(range(10))
    assert [m for i, m in out if i % 3] == [f"m{i}" for i in range(10) if i % 3]
    assert all(m is None for i, m in out if i % 3 == 0)
    assert events == [("submit", 0), ("submit", 1), ("collect", 0), ("submit", 2),
                      ("collect", 1), ("collect", 2)]


def test_results_do_not_depend_on_the_cpu_thread_count(loop_bag, tmp_path, monkeypatch):
    """Loops, loop measurement and pair matching run on CPU threads (the measurement on
    processes): the stages on explicit inputs with one thread give what the run with three
    wrote, and so do two worker processes, and a matcher that matches pairs in batches."""
    import functools

    import cusfm_ros.pipeline.stages.pose_graph as pose_graph_stage
    from cusfm_ros.pipeline.parallel import process_map
    from cusfm_ros.core.features.knn import KnnMatcher
    from cusfm_ros.io.feature_store import FeatureStore
    from cusfm_ros.io.loops_file import read_loops, write_loops
    from cusfm_ros.io.pairs_file import read_pairs
    from cusfm_ros.io.tum import read_tum
    from cusfm_ros.io.vocabulary_file import load_vocabulary
    from cusfm_ros.pipeline.stages.loops import detect_loops
    from cusfm_ros.pipeline.stages.matching import match_pairs
    from cusfm_ros.pipeline.stages.pose_graph import optimize_pose_graph
    from cusfm_ros.pipeline.stores import load_keyframes, open_features

    run = RunDir(tmp_path / "run")
    assert main(["map", str(loop_bag / "bag"), "--out", str(run.root), "--cpu-threads", "3",
                 "--steps", "keyframes", "features", "vocabulary", "loops", "pose_graph",
                 "pairs", "matching", *FAST]) == 0
    options = _sift_options()
    keyframes = load_keyframes(run)
    with open_features(run, options) as store:
        features = {k.image_name: store.features(k.image_name) for k in keyframes.keyframes}
        loops, _ = detect_loops(keyframes, features, load_vocabulary(run.vocabulary),
                                KnnMatcher(), options.loops, 0, threads=1)
        assert len(loops) == len(read_loops(run.loops)) > 0
        write_loops(tmp_path / "one_thread.json", loops, keyframes)
        assert (tmp_path / "one_thread.json").read_bytes() == run.loops.read_bytes()
        # a matcher with a batched path (the torch LightGlue's) gets the candidates a batch
        # at a time, in the calling thread, and the verification threads get them matched
        batched = _BatchedKnn()
        loops_batched, counts = detect_loops(keyframes, features,
                                             load_vocabulary(run.vocabulary), batched,
                                             options.loops, 0, threads=2)
        write_loops(tmp_path / "batched.json", loops_batched, keyframes)
        assert (tmp_path / "batched.json").read_bytes() == run.loops.read_bytes()
        assert max(batched.batches) == 3
        assert sum(batched.batches) == counts["verified_candidates"] > len(loops_batched)
        one_at_a_time = []

        class CountingKnn(KnnMatcher):
            def match(self, features0, features1):
                one_at_a_time.append(1)
                return super().match(features0, features1)

        graph = optimize_pose_graph(keyframes, loops, features, CountingKnn(),
                                    options.pose_graph, "rig", 0, threads=1)
        written = read_tum(run.pose_graph_poses)
        assert np.array_equal(graph.world_from_rig.stamps_ns, written.stamps_ns)
        assert np.allclose(graph.world_from_rig.world_from_body, written.world_from_body,
                           atol=1e-6)
        # the loop measurement's matches through the batched path (query-match, then
        # partner-match pairs), remembered in the cache as computed
        batched, cached = _BatchedKnn(), _BatchedKnn()
        on_batches = optimize_pose_graph(keyframes, loops, features, batched,
                                         options.pose_graph, "rig", 0, threads=2)
        np.testing.assert_array_equal(on_batches.world_from_rig.world_from_body,
                                      graph.world_from_rig.world_from_body)
        assert max(batched.batches) == 3
        assert sum(batched.batches) == len(one_at_a_time) >= len(loops)
        with FeatureStore(tmp_path / "graph_cache.h5", {}) as graph_cache:
            with_cache = optimize_pose_graph(keyframes, loops, features, cached,
                                             options.pose_graph, "rig", 0, graph_cache,
                                             threads=2)
            remembered = graph_cache.pairs()
            for name0, name1 in remembered:
                np.testing.assert_array_equal(
                    graph_cache.matches(name0, name1).indices,
                    KnnMatcher().match(features[name0], features[name1]).indices)
        np.testing.assert_array_equal(with_cache.world_from_rig.world_from_body,
                                      graph.world_from_rig.world_from_body)
        # a pair that comes again is read from the cache once it is there
        assert 0 < len(remembered) <= sum(cached.batches) <= sum(batched.batches)
        # the loop measurements on two spawned worker processes (this bag has too few loops
        # for the default minimum; two chunks of two at least)
        assert len(loops) >= 4
        monkeypatch.setattr(pose_graph_stage, "process_map",
                            functools.partial(process_map, chunk=2, minimum=1))
        on_processes = optimize_pose_graph(keyframes, loops, features, KnnMatcher(),
                                           options.pose_graph, "rig", 0, threads=2)
        assert on_processes.summary["loop_edges"] == graph.summary["loop_edges"] > 0
        np.testing.assert_array_equal(on_processes.world_from_rig.world_from_body,
                                      graph.world_from_rig.world_from_body)
        pairs = read_pairs(run.pairs)
        cameras = {k.image_name: keyframes.rig[k.camera_name].camera
                   for k in keyframes.keyframes}
        # the raw matches cached by the loops and pose graph stages, as the run had them
        import shutil

        import h5py
        shutil.copy(run.raw_matches, tmp_path / "raw.h5")
        with h5py.File(tmp_path / "raw.h5", "r") as raw:
            raw_config = json.loads(raw.attrs["config"])
        with FeatureStore(tmp_path / "one_thread.h5", {}) as mine, \
                FeatureStore(tmp_path / "raw.h5", raw_config) as cache, \
                FeatureStore(run.verified_matches, {}, read_only=True) as theirs:
            match_pairs(pairs, cameras, store, KnnMatcher(), options.matching, 0, mine, cache,
                        threads=1)
            for name0, name1 in pairs:
                assert np.array_equal(mine.matches(name0, name1).indices,
                                      theirs.matches(name0, name1).indices)
        # no cache: every pair through the batched path, against one at a time
        with FeatureStore(tmp_path / "batched.h5", {}) as mine, \
                FeatureStore(tmp_path / "plain.h5", {}) as theirs:
            match_pairs(pairs, cameras, store, KnnMatcher(), options.matching, 0, theirs,
                        threads=1)
            batched = _BatchedKnn()
            counts = match_pairs(pairs, cameras, store, batched, options.matching, 0, mine,
                                 threads=2)
            assert counts["matcher_runs"] == len(pairs) == sum(batched.batches)
            assert batched.batches == [3] * (len(pairs) // 3) + [len(pairs) % 3] * (
                len(pairs) % 3 > 0)
            for name0, name1 in pairs:
                assert np.array_equal(mine.matches(name0, name1).indices,
                                      theirs.matches(name0, name1).indices)
    assert main(["map", str(loop_bag / "bag"), "--out", str(tmp_path / "bad"),
                 "--cpu-threads", "-1"]) == 1


def test_loop_candidates_stand_for_their_stereo_pairs(loop_bag, tmp_path):
    """With ``by_stereo_pair`` (the default) each pair of stereo pairs among the candidates
    is matched once, from both query images to one match image (the two pairs of the pose
    graph's stereo measurement), where image-by-image candidates matched up to four image
    pairs for the same two places; the places whose loops are found stay the same."""
    from dataclasses import replace

    from cusfm_ros.core.features.knn import KnnMatcher
    from cusfm_ros.io.vocabulary_file import load_vocabulary
    from cusfm_ros.pipeline.stages.loops import StereoPairs, detect_loops
    from cusfm_ros.pipeline.stores import load_keyframes, open_features

    run = RunDir(tmp_path / "run")
    assert main(["map", str(loop_bag / "bag"), "--out", str(run.root), "--steps",
                 "keyframes", "features", "vocabulary", *FAST]) == 0
    options = _sift_options()
    keyframes = load_keyframes(run)
    pairs = StereoPairs(keyframes)
    images = {k.image_name: k for k in keyframes.keyframes}

    class Recording(KnnMatcher):
        def __init__(self):
            super().__init__()
            self.pairs = []

        def match(self, features0, features1):
            self.pairs.append((features0, features1))
            return super().match(features0, features1)

    with open_features(run, options) as store:
        features = {k.image_name: store.features(k.image_name) for k in keyframes.keyframes}
        name_of = {id(f): name for name, f in features.items()}
        found = {}
        for by_pair in (True, False):
            matcher = Recording()
            loops, counts = detect_loops(
                keyframes, features, load_vocabulary(run.vocabulary), matcher,
                replace(options.loops, by_stereo_pair=by_pair), 0, threads=1)
            matched = [(images[name_of[id(a)]], images[name_of[id(b)]]) for a, b in matcher.pairs]
            assert counts["verified_candidates"] == len(matched)
            found[by_pair] = loops, matched
    loops, matched = found[True]
    groups = {}
    for query, match in matched:
        groups.setdefault((pairs.key(query), pairs.key(match)), []).append((query, match))
    assert len(groups) > 10 and all(len(g) == 2 for g in groups.values())
    for (q0, m0), (q1, m1) in groups.values():
        assert m0 is m1 and q0.sample_id == q1.sample_id and q0.camera_name != q1.camera_name
    old_loops, old_matched = found[False]
    assert {(pairs.key(q), pairs.key(m)) for q, m in old_matched} == set(groups)
    assert len(matched) < len(old_matched)

    def places(records):
        return {(images[x.query_image].sample_id, images[x.match_image].sample_id)
                for x in records}
    assert len(places(loops)) >= 0.9 * len(places(old_loops))
