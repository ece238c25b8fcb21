"""One-off, exploratory: average the weights of adapter bundles fine-tuned from the same adapter.

    python average_adapters.py OUT BUNDLE [BUNDLE ...]
"""

import json
import sys
from pathlib import Path

from safetensors import safe_open
from safetensors.torch import load_file, save_file

out, sources = Path(sys.argv[1]), [Path(p) for p in sys.argv[2:]]
tensors = [load_file(str(p / "adapter.safetensors")) for p in sources]
average = {k: (sum(t[k].float() for t in tensors) / len(tensors)).to(tensors[0][k].dtype) for k in tensors[0]}
out.mkdir(parents=True, exist_ok=False)
with safe_open(str(sources[0] / "adapter.safetensors"), "pt") as f:
    metadata = f.metadata()
save_file(average, str(out / "adapter.safetensors"), metadata=metadata)
config = json.loads((sources[0] / "config.json").read_text())
config["card"] = {**config["card"], "soup_of": [str(p) for p in sources]}
(out / "config.json").write_text(json.dumps(config, indent=2) + "\n")
print(f"average of {len(tensors)} -> {out}")
