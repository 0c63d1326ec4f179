"""Local features and matching: ALIKED and LightGlue through ONNX Runtime, SIFT, k-NN.

Extractors take an image (H, W) or (H, W, 3) and return ``Features``; matchers take two
``Features`` and return ``Matches``. Nothing here imports torch.
"""
