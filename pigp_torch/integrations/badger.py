r"""pigp-torch in Badger: the ``pigp_physics`` generator and the ``pigp_sim`` environment.

How Badger 1.6 finds things, and what :func:`setup` (``pigp badger-setup``) does about it:

* Badger reads its settings from its own config file (``~/.config/config.yaml`` on Linux,
  written by ``badger config`` / the GUI), not from the environment; it does not create that
  folder. :func:`setup` creates it and, on a first use, runs Badger's own first-use set-up
  (plugin, template, logbook and archive folders under ``~/.local/share/Badger``); an existing
  configuration is kept.
* Environments are folders ``<plugin root>/environments/<name>`` (``configs.yaml`` and a module
  with an ``Environment`` class). :func:`setup` copies ``pigp_sim`` there; its class lives in
  :mod:`pigp_torch.badger_plugins.sim_ring`, so upgrading pigp-torch upgrades it.
* Generators are Xopt's registry as seen in Badger's own process: Badger 1.6 loads no generator
  plugins and neither Badger nor Xopt reads package entry points, so ``pigp_physics`` is listed
  only once :mod:`pigp_torch.integrations.xopt_physics` is imported there. :func:`setup` writes a
  one-line start-up file (``pigp_torch_badger.pth``) into the Python environment's
  ``site-packages``: at interpreter start it only installs :func:`watch_badger`, an import hook
  that registers the generator right after ``badger.factory`` (Badger's plugin registry) is
  imported, in every Badger process (CLI, GUI and its routine processes). Nothing else is
  imported at start-up; a process that never imports Badger is not affected.

Headless routines: :func:`run_routine` runs a Badger ``Routine`` through Badger's own loop
(``badger.core.run_routine``) and ends it with the environment's :meth:`end_routine
<pigp_torch.badger_plugins.sim_ring.SimRingEnvironment.end_routine>` (knobs restored), inside
the routine's life, also on errors and Ctrl-C. A script that calls ``badger.core.run_routine``
itself is covered too: the environment ends a routine it was never told the end of at the next
routine's start, at its garbage collection, or when the process ends.
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import shutil
import sys
import sysconfig
import warnings
from collections.abc import Callable
from pathlib import Path

#: Knobs of the ``pigp_sim`` environment (the 13 skew windings of the study), in amps.
SIM_KNOBS = (
    "01G-QSS4", "02G-QSS3", "05G-QSS3", "07G-QSS2", "08G-QSS2", "09G-QSS1", "10G-QSS4",
    "11G-QSS3", "12G-QSS3", "14G-QSS2", "16G-QSS2", "17G-QSS2", "18G-QSS1",
)  # fmt: skip
SIM_LIMIT_A = 30.0
OBJECTIVE_PV = "SPEAR:BeamLossRate"
ENVIRONMENT = "pigp_sim"
GENERATOR = "pigp_physics"

#: The start-up file :func:`setup` writes into ``site-packages`` (one ``import`` line; Python's
#: ``site`` module runs it at interpreter start; it never fails the start-up).
STARTUP_FILE = "pigp_torch_badger.pth"
STARTUP_LINE = (
    'import sys; exec("try:\\n from pigp_torch.integrations.badger import watch_badger\\n'
    'except Exception:\\n pass\\nelse:\\n watch_badger()")\n'
)


def plugin_root() -> Path:
    """The folder of pigp's Badger plugins shipped with the package (``environments/pigp_sim``);
    registers the ``pigp_physics`` generator with Xopt (and so with Badger) in this process."""
    register_generator()
    return Path(__file__).resolve().parents[1] / "badger_plugins"  # pigp_torch/badger_plugins


def _shipped_environment() -> Path:
    return Path(__file__).resolve().parents[1] / "badger_plugins" / "environments" / ENVIRONMENT


def install_plugins(root: str | Path, *, replace: bool = False) -> Path:
    """Copy the ``pigp_sim`` environment into the Badger plugin root ``root``; returns its folder.

    Raises:
        FileExistsError: ``root`` already has a ``pigp_sim`` environment and ``replace`` is
            false (with ``replace`` it is overwritten).
    """
    target = Path(root) / "environments" / ENVIRONMENT
    if target.exists():
        if not replace:
            raise FileExistsError(f"{target} exists")
        shutil.rmtree(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(
        _shipped_environment(), target, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
    )
    return target


# -- the generator in Badger's processes ----------------------------------------------------------
def register_generator() -> bool:
    """Register ``pigp_physics`` in Xopt's generator registry (the one Badger lists).

    Returns:
        ``True`` when registered; ``False`` (with a warning) when Xopt or pigp's generator cannot
        be imported.
    """
    try:
        import pigp_torch.integrations.xopt_physics  # noqa: F401  (registers at import)
    except Exception as err:  # a broken extra must not stop Badger itself
        warnings.warn(f"pigp_physics is not available in Badger: {err}", stacklevel=2)
        return False
    return True


class _AfterBadgerFactory(importlib.abc.MetaPathFinder):
    """Import hook: lets ``badger.factory`` import as usual, then registers the generator."""

    def find_spec(self, fullname, path, target=None):
        if fullname != "badger.factory":
            return None
        sys.meta_path.remove(self)  # one shot; the real finders locate the module
        spec = importlib.util.find_spec(fullname)
        if spec is None or spec.loader is None:
            return spec
        exec_module = spec.loader.exec_module

        def exec_then_register(module):
            exec_module(module)
            register_generator()

        spec.loader.exec_module = exec_then_register
        return spec


def watch_badger() -> None:
    """Register ``pigp_physics`` as soon as Badger's plugin registry (``badger.factory``) is
    imported in this process (at once if it already is). Cheap: imports nothing itself."""
    if "badger.factory" in sys.modules:
        register_generator()
    elif not any(isinstance(f, _AfterBadgerFactory) for f in sys.meta_path):
        sys.meta_path.insert(0, _AfterBadgerFactory())


def startup_file(site_dir: str | Path | None = None) -> Path:
    """Where :func:`setup` writes :data:`STARTUP_FILE`: ``site_dir`` or this environment's
    ``site-packages`` (``sysconfig`` purelib)."""
    base = Path(site_dir) if site_dir is not None else Path(sysconfig.get_paths()["purelib"])
    return base / STARTUP_FILE


# -- Badger's configuration -----------------------------------------------------------------------
#: Folder settings all unset on a first use of Badger (its log folder has a default).
_FIRST_USE_KEYS = (
    "BADGER_PLUGIN_ROOT", "BADGER_TEMPLATE_ROOT", "BADGER_LOGBOOK_ROOT", "BADGER_ARCHIVE_ROOT",
)  # fmt: skip


def setup(*, site_dir: str | Path | None = None, startup_hook: bool = True) -> dict[str, str]:
    """Make Badger 1.6 show pigp's plugins for the current user and Python environment.

    1. Create Badger's config folder (``~/.config`` on Linux) if missing; with no plugin root
       configured, run Badger's own first-use set-up (``badger.settings.mock_settings``: plugin,
       template, logbook and archive folders under ``~/.local/share/Badger``, its example
       plugins); fill any other unset folder setting the same way; keep what is set.
    2. Copy (or update) the ``pigp_sim`` environment into the plugin root.
    3. With ``startup_hook``, write :data:`STARTUP_FILE` (see the module docstring) into
       ``site_dir`` (default: this environment's ``site-packages``).

    Returns:
        ``{"config": ..., "plugin root": ..., "environment": ..., "startup file": ...}`` (paths;
        ``"startup file"`` is ``"not written"`` without ``startup_hook``).

    Raises:
        ImportError: Badger is not installed (``pip install "pigp-torch[badger]"``).
        OSError: a folder or file cannot be written (e.g. a read-only ``site-packages``: pass
            ``startup_hook=False`` and import ``pigp_torch.integrations.xopt_physics`` yourself).
    """
    try:
        from badger.settings import get_user_config_folder
    except ImportError as err:
        raise ImportError('Badger is not installed: pip install "pigp-torch[badger]"') from err
    Path(get_user_config_folder()).mkdir(parents=True, exist_ok=True)  # Badger does not
    from badger.settings import init_settings, mock_settings
    from badger.utils import get_datadir

    settings = init_settings()
    paths = settings.list_path_settings()
    root = paths.get("BADGER_PLUGIN_ROOT")
    if not root or not Path(root).is_dir():
        if all(paths.get(k) is None for k in _FIRST_USE_KEYS):
            mock_settings()  # Badger's first-use set-up, as `badger` offers interactively
        else:
            root = get_datadir() / "Badger" / "plugins"
            root.mkdir(parents=True, exist_ok=True)
            settings.write_value("BADGER_PLUGIN_ROOT", str(root))
    for key, value in settings.list_path_settings().items():
        if value is None:  # Badger asks for every unset folder at start; give each one
            folder = get_datadir() / "Badger" / key.removeprefix("BADGER_").lower()
            folder.mkdir(parents=True, exist_ok=True)
            settings.write_value(key, str(folder))
    root = Path(settings.read_value("BADGER_PLUGIN_ROOT"))
    env_dir = install_plugins(root, replace=True)
    done = {
        "config": str(settings.config_path),
        "plugin root": str(root),
        "environment": str(env_dir),
        "startup file": "not written",
    }
    if startup_hook:
        path = startup_file(site_dir)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(STARTUP_LINE)
        done["startup file"] = str(path)
    return done


# -- headless routines ----------------------------------------------------------------------------
def run_routine(
    routine,
    *,
    max_evaluations: int | None = None,
    active_callback: Callable[[], int] | None = None,
    generate_callback: Callable | None = None,
    evaluate_callback: Callable | None = None,
    states_callback: Callable | None = None,
    verbose: int = 0,
):
    """Run a Badger ``routine`` headless with Badger's own loop and end it properly.

    Calls ``badger.core.run_routine`` (the initial points — default: the variables' values now,
    as Badger's "Add Current" — then generate / evaluate until the ``active_callback`` says
    2 = stop) and, when it returns or raises — the stop, an error, Ctrl-C — the environment's
    ``end_routine()`` if it has one (``pigp_sim``: the knobs set back to those found at the
    start, or to the best reading, see its ``end_knobs``), while the process and its Channel
    Access client are still fully alive.

    Args:
        routine: a ``badger.routine.Routine``.
        max_evaluations: stop once the routine's data has this many rows (initial points
            included); ignored when ``active_callback`` is given. One of the two is required.
        active_callback, generate_callback, evaluate_callback, states_callback, verbose:
            as in ``badger.core.run_routine`` (callbacks optional here).

    Returns:
        the routine's data (``pandas.DataFrame``).

    Raises:
        ValueError: neither ``max_evaluations`` nor ``active_callback``.
        whatever the routine raised (Badger's normal stop, ``BadgerRunTerminated``, is not an
        error); a failed restore (``MachineError``), chained to the routine's error if any.
    """
    from badger.core import run_routine as badger_run_routine
    from badger.errors import BadgerRunTerminated

    if active_callback is None:
        if max_evaluations is None:
            raise ValueError("give max_evaluations or an active_callback (else it never stops)")
        n = int(max_evaluations)

        def active_callback() -> int:
            data = routine.data
            return 2 if data is not None and len(data) >= n else 0

    if routine.initial_points is None or not len(routine.initial_points):
        import pandas as pd

        names = routine.vocs.variable_names  # start where the machine is (Badger's "add current")
        routine.initial_points = pd.DataFrame([routine.environment.get_variables(names)])
    try:
        badger_run_routine(
            routine,
            active_callback,
            generate_callback or (lambda candidates: None),
            evaluate_callback,
            states_callback,
            verbose=verbose,
        )
    except BadgerRunTerminated:
        pass
    finally:
        end = getattr(routine.environment, "end_routine", None)
        if end is not None:
            end()
    return routine.data


def main(argv: list[str] | None = None) -> int:
    """``python -m pigp_torch.integrations.badger setup`` (the same as ``pigp badger-setup``)."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m pigp_torch.integrations.badger")
    sub = parser.add_subparsers(dest="action", required=True)
    add_setup_arguments(sub.add_parser("setup", help=SETUP_HELP, description=SETUP_DESCRIPTION))
    args = parser.parse_args(argv)
    return cmd_setup(args)


SETUP_HELP = "make Badger list pigp_physics and the pigp_sim environment"
SETUP_DESCRIPTION = (
    "Set Badger 1.6 up for pigp-torch: create Badger's config file (~/.config/config.yaml) and "
    "its folders on a first use (an existing configuration is kept), copy the pigp_sim "
    "environment (the simulated ring of `pigp serve-sim` over Channel Access) into Badger's "
    "plugin root, and write a one-line start-up file into this Python environment's "
    "site-packages so that every Badger process lists the pigp_physics generator. Run it again "
    "after upgrading; delete the start-up file it prints to undo that part."
)


def add_setup_arguments(p) -> None:
    p.add_argument(
        "--site-dir",
        default=None,
        help="folder for the start-up file (default: this environment's site-packages)",
    )
    p.add_argument(
        "--no-startup-hook",
        action="store_true",
        help="do not write the start-up file (then import pigp_torch.integrations.xopt_physics "
        "in Badger's process yourself to see pigp_physics)",
    )


#: How to serve the simulated ring for the ``pigp_sim`` environment (the port is ``pigp
#: serve-sim``'s default, :data:`pigp_torch.simulated_epics.SIM_CA_PORT`: not CA's standard 5064).
SERVE_HINT = (
    "serve the ring with `pigp serve-sim &` (Channel Access on 127.0.0.1:5164, its default port) "
    "and give the environment ca_port 5164"
)


def cmd_setup(args) -> int:
    try:
        done = setup(site_dir=args.site_dir, startup_hook=not args.no_startup_hook)
    except (ImportError, OSError) as err:
        print(f"badger setup: error: {err}", file=sys.stderr)
        return 2
    width = max(len(k) for k in done)
    for key, value in done.items():
        print(f"{key:<{width}} : {value}")
    print(f"next: `badger generator` lists {GENERATOR}, `badger env` lists {ENVIRONMENT}; ", end="")
    print(SERVE_HINT)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
