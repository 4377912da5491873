"""How far each body lies from the bodies the recurrent network was trained on: the z-scores of its body code
(joint offsets, girths and height, :func:`retarget_core.model.features.target_rig`) under the network's own
normalisation (``target_mean``/``target_std`` in the shipped weights), root mean square and largest.

    PYTHONPATH=. python benchmarks/diag/body_code_distance.py ../shared/data/characters/*.glb ../shared/data/rigs/*
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from retarget_core.body_parts import body_parts
from retarget_core.loading import load_character
from retarget_core.model.features import target_rig
from retarget_core.model.inference import WEIGHTS_PATH


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bodies", nargs="+", type=Path, help="target characters (GLB, glTF, VRM, FBX)")
    a = ap.parse_args()
    state = torch.load(WEIGHTS_PATH, map_location="cpu", weights_only=False)["state"]
    mean, std = state["target_mean"], state["target_std"]
    for path in a.bodies:
        loaded = load_character(path)
        ch, mapping = loaded.character, loaded.mapping
        rig = target_rig(ch.skeleton, mapping, ch.vertices, body_parts(ch, mapping))
        z = ((rig.code - mean) / std).abs()
        print(f"{path.name:32s} height {ch.height:.2f} m  rms z {float(z.pow(2).mean().sqrt()):6.2f}  "
              f"largest {float(z.max()):7.2f} (code entry {int(z.argmax())} of {len(z)})")  # fmt: skip


if __name__ == "__main__":
    main()
