"""Alias: :mod:`pigp_torch.simulated_epics.ioc_process` under its old path (the module itself)."""

import sys

from pigp_torch.simulated_epics import ioc_process as _moved

if __name__ == "__main__":  # python -m pigp_torch.testing.ioc_process
    import runpy

    runpy.run_module(_moved.__name__, run_name="__main__", alter_sys=True)
else:
    sys.modules[__name__] = _moved
