"""`pigp demo` runs its pipeline on one torch thread, as the benchmark's runs do."""

import torch

from pigp_torch.bench import demo


def test_run_demo_uses_one_thread_and_restores_the_count(monkeypatch):
    seen = []

    def pipeline(settings):
        seen.append(torch.get_num_threads())
        return "runs", "prior"

    monkeypatch.setattr(demo, "_run_demo", pipeline)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        assert demo.run_demo(demo.DemoSettings()) == ("runs", "prior")
        assert seen == [1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
