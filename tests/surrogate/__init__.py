"""Tests of pigp_torch.surrogate and surrogate_training (a package: unique module names)."""
