"""One module per mapper stage; each has a ``Stage`` subclass and a function on explicit
inputs. The order lives in ``pipeline/registry.py``."""
