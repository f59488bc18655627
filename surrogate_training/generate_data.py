"""Generate simulated coupling data: ``python surrogate_training/generate_data.py --n N -o FILE``.

The same as ``pigp generate-data`` (see ``--help``); the sampling design is documented in
:mod:`pigp_torch.data.sampling`.
"""

import sys

from pigp_torch.cli import main

if __name__ == "__main__":
    sys.exit(main(["generate-data", *sys.argv[1:]]))
