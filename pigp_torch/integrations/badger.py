r"""pigp-torch in Badger: the ``pigp_physics`` generator and the ``pigp_sim`` environment.

Badger 1.x lists Xopt's generator registry, so importing
:mod:`pigp_torch.integrations.xopt_physics` (done by :func:`plugin_root`) makes ``pigp_physics``
a Badger generator. The environment is a Badger plugin folder shipped with the package:
``plugin_root()/environments/pigp_sim`` (the simulated ring of ``pigp serve-sim`` over Channel
Access). Point Badger at it with ``BADGER_PLUGIN_ROOT=$(python -c "import
pigp_torch.integrations.badger as b; print(b.plugin_root())")``, or copy the folder into your own
plugin root (:func:`install_plugins`).
"""

from __future__ import annotations

import shutil
from pathlib import Path

#: Knobs of the ``pigp_sim`` environment (the 13 skew windings of the study), in amps.
SIM_KNOBS = (
    "01G-QSS4", "02G-QSS3", "05G-QSS3", "07G-QSS2", "08G-QSS2", "09G-QSS1", "10G-QSS4",
    "11G-QSS3", "12G-QSS3", "14G-QSS2", "16G-QSS2", "17G-QSS2", "18G-QSS1",
)  # fmt: skip
SIM_LIMIT_A = 30.0
OBJECTIVE_PV = "SPEAR:BeamLossRate"


def plugin_root() -> Path:
    """The folder of pigp's Badger plugins (``environments/pigp_sim``); registers the
    ``pigp_physics`` generator with Xopt (and so with Badger)."""
    import pigp_torch.integrations.xopt_physics  # noqa: F401  (registration)

    return Path(__file__).resolve().parents[1] / "badger_plugins"  # pigp_torch/badger_plugins


def install_plugins(root: str | Path) -> Path:
    """Copy pigp's plugin folders into a Badger plugin root ``root``; returns the environment's
    folder. Raises ``FileExistsError`` when ``root`` already has a ``pigp_sim`` environment."""
    target = Path(root) / "environments" / "pigp_sim"
    if target.exists():
        raise FileExistsError(f"{target} exists")
    shutil.copytree(plugin_root() / "environments" / "pigp_sim", target)
    return target
