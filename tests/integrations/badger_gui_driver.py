"""Badger's GUI, driven in-process through its Qt objects (run under Xvfb, with a HOME set up by
``pigp badger-setup``): ``python badger_gui_driver.py OUT_DIR [--run PRIOR.json]`` prints one JSON
line and writes screenshots of the whole X screen into OUT_DIR.

1. ``generators.png``: the main window with the routine editor's generator list opened.
2. With ``--run``: a routine template (environment ``pigp_sim`` on a simulated IOC started here,
   the 13 windings, ``loss_rate`` MAXIMIZE, generator ``pigp_physics`` with the prior file) is
   loaded as a click on it in the Templates tab does, and run with the termination condition
   "5 evaluations" as the GUI's "run until" does (the routine runs in Badger's routine process);
   ``algorithm.png`` shows the generator's settings from the template, ``run.png`` the run
   monitor after the run. The same routine then runs again and is stopped with the Stop
   button's slot after 3 readings (``"stopped"``). The JSON gives the knobs' setpoints at the
   start and after each run (A).
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import yaml
from PyQt5.QtCore import QEventLoop, QTimer
from PyQt5.QtWidgets import QApplication


def wait(ms: int) -> None:
    loop = QEventLoop()
    QTimer.singleShot(ms, loop.quit)
    loop.exec_()


def shoot(app, path: Path) -> None:
    app.primaryScreen().grabWindow(0).save(str(path), "PNG")


def template(prior: str, port: int) -> dict:
    from pigp_torch.integrations.badger import SIM_KNOBS

    return {
        "name": "pigp-physics on pigp_sim",
        "description": "pigp_physics on the simulated ring; knobs set back at the end",
        "relative_to_current": False,
        "generator": {"name": "pigp_physics", "prior_file": prior, "max_travel_distances": 0.1,
                      "n_starts": 2},
        "environment": {"name": "pigp_sim",
                        "params": {"ca_port": port, "timeout": 5.0, "end_knobs": "initial"}},
        "vrange_limit_options": {
            k: {"limit_option_idx": 0, "ratio_curr": 0.1, "ratio_full": 0.1} for k in SIM_KNOBS
        },
        "vrange_hard_limit": {},
        "initial_point_actions": [{"type": "add_curr"}],
        "critical_constraint_names": [],
        "additional_variables": [],
        "formulas": {},
        "constraint_formulas": {},
        "observable_formulas": {},
        "vocs": {
            "variables": {k: [-30.0, 30.0] for k in SIM_KNOBS},
            "objectives": {"loss_rate": "MAXIMIZE"},
            "constraints": {},
            "observables": [],
        },
    }  # fmt: skip


def show_tab(editor, widget) -> None:
    """Bring the routine editor's tab holding ``widget`` to the front (a click on the tab)."""
    from PyQt5.QtWidgets import QTabWidget

    for tabs in editor.findChildren(QTabWidget):
        if (i := tabs.indexOf(widget)) >= 0:
            tabs.setCurrentIndex(i)


def main() -> None:
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    prior = sys.argv[3] if len(sys.argv) > 3 and sys.argv[2] == "--run" else None

    from qdarkstyle import DarkPalette, load_stylesheet

    app = QApplication(sys.argv[:1])
    app.setStyleSheet(load_stylesheet(palette=DarkPalette))  # as `badger -g` (theme dark)
    from badger.gui.windows.main_window import BadgerMainWindow

    window = BadgerMainWindow()
    window.resize(1900, 1050)
    window.move(0, 0)
    window.show()
    deadline = time.monotonic() + 60.0
    while window.thread_list and time.monotonic() < deadline:  # routine processes spawned
        wait(200)
    wait(1000)
    editor = window.home_page.routine_editor
    cb = editor.generator_box.cb
    show_tab(editor, editor.generator_box)
    listed = [cb.itemText(i) for i in range(cb.count())]
    cb.setCurrentIndex(listed.index("pigp_physics"))
    wait(500)
    cb.showPopup()
    wait(800)
    shoot(app, out / "generators.png")
    cb.hidePopup()
    result = {"generators": listed, "selected": cb.currentText()}

    if prior is not None:
        from caproto.threading.client import Context

        from pigp_torch.integrations.badger import SIM_KNOBS
        from pigp_torch.simulated_epics.ioc import start_sim_ioc

        start = [round(1.2 * math.cos(2.0 * k), 6) for k in range(len(SIM_KNOBS))]
        with start_sim_ioc(1, update_period=0.05) as ioc:
            ctx = Context(timeout=5.0)
            pvs = ctx.get_pvs(*ioc.setpoint_pvs, timeout=5.0)
            for pv, value in zip(pvs, start, strict=True):
                pv.wait_for_connection(timeout=5.0)
                pv.write([value], wait=True, timeout=5.0)
            path = out / "pigp_template.yaml"
            path.write_text(yaml.safe_dump(template(prior, ioc.port)))
            editor.load_template_yaml(False, template_path=str(path))  # a click in Templates
            wait(1500)
            show_tab(editor, editor.generator_box)
            wait(500)
            shoot(app, out / "algorithm.png")
            show_tab(editor, editor.env_box)
            home = window.home_page
            home.run_monitor.termination_condition = {"tc_idx": 0, "max_eval": 5}
            home.start_run(use_termination_condition=True)  # as the "run until" dialog does
            deadline = time.monotonic() + 240.0
            wait(1000)
            while home.run_monitor.running and time.monotonic() < deadline:
                wait(250)
            wait(1500)
            shoot(app, out / "run.png")
            data = home.run_monitor.routine.data
            end = [float(pv.read(timeout=5.0).data[0]) for pv in pvs]
            moved = 0.0
            if data is not None and len(data):
                moved = max(
                    abs(float(data[k].iloc[i]) - start[j])
                    for j, k in enumerate(SIM_KNOBS)
                    for i in range(len(data))
                )
            result.update(
                start=start, end=end, n=0 if data is None else len(data), moved=moved,
                finished=not home.run_monitor.running,
            )  # fmt: skip
            # a second run of the same routine, stopped with the Stop button's slot
            home.run_monitor.termination_condition = None
            home.start_run(use_termination_condition=False)
            deadline = time.monotonic() + 240.0
            n = 0
            while time.monotonic() < deadline:
                wait(100)
                data = home.run_monitor.routine.data
                n = 0 if data is None else len(data)
                if n >= 3:
                    home.run_monitor.stop()  # the Stop button
                    break
            while home.run_monitor.running and time.monotonic() < deadline:
                wait(250)
            wait(1000)
            end2 = [float(pv.read(timeout=5.0).data[0]) for pv in pvs]
            result["stopped"] = {"n": n, "end": end2, "running": home.run_monitor.running}
            ctx.disconnect()
    window.process_manager.close_proccesses()
    print(json.dumps(result))
    sys.stdout.flush()
    window.close()


if __name__ == "__main__":
    main()
