"""Reports of finished and running runs: the HTML report of a run log
(:mod:`~pigp_torch.reporting.report`) and the live dashboard
(:mod:`~pigp_torch.reporting.dashboard`). Importing this package imports neither.
"""
