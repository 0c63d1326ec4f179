"""PyTorch network definitions (build time and the torch backend only)."""
