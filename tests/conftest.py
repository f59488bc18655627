"""Test-suite setup: single-threaded BLAS (numpy's 6x6 stacks crawl with contended threads)."""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
