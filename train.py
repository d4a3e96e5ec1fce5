"""Train a neural BRDF from a YAML config: a thin shim over ``neural-brdf train``.

    python train.py configs/quickstart.yaml                      # -> runs/quickstart/
    python train.py configs/gold.yaml --out runs/gold --set train.steps=2000
    python train.py configs/gold.yaml --out runs/gold --resume   # continue after Ctrl-C

Each run directory gets config.yaml (resolved), ckpt.pt, log.csv, model.onnx and
metrics.json.  Exit codes: 0 ok, 1 a physics check failed, 2 bad input.
"""

import sys

from neural_brdf.tooling.cli import main

if __name__ == "__main__":
    sys.exit(main(["train", *sys.argv[1:]]))
