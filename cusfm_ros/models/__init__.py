"""Learned models: our own PyTorch definitions of ALIKED and LightGlue (build time only), their
ONNX export, and the model cache that the runtime reads (``store.py``, no torch needed).

Only ``nets/`` and ``build.py`` import torch; nothing on the runtime path does.
"""
