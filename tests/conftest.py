"""Test-suite setup: single-threaded BLAS (numpy's 6x6 stacks crawl with contended threads)."""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# `pigp demo` caches between runs; the tests use a fresh folder of their own, never ~/.cache.
if not os.environ.get("PIGP_CACHE_DIR"):
    import tempfile

    os.environ["PIGP_CACHE_DIR"] = tempfile.mkdtemp(prefix="pigp-test-cache-")
