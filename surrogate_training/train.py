"""Train the loss-rate surrogate: ``python surrogate_training/train.py DATA.npz -o MODEL.pt``.

The same as ``pigp train-surrogate`` (see ``--help``): an ensemble of smooth MLPs, saved with its
provenance (knob names, bounds, f_inf, the dataset's metadata, held-out metrics).
"""

import sys

from pigp_torch.cli import main

if __name__ == "__main__":
    sys.exit(main(["train-surrogate", *sys.argv[1:]]))
