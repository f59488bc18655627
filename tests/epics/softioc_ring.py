"""A real EPICS base IOC (pythonSoftIOC) serving a small two-knob test ring, for the test that
runs `pigp optimize` against an IOC other than our own caproto one.

Run as a script (``python tests/epics/softioc_ring.py --put-log FILE --x-init 2.5,-1.25``) with
the server environment of :func:`pigp_torch.simulated_epics.ca_env.server_environment` (127.0.0.1
only). Per knob an ``ao`` setpoint ``<knob>:CurrSetpt`` (DRVL/DRVH = the bounds) and an ``ai``
readback ``<knob>:Curr1`` that follows it at once; ``TEST:BeamLossRate`` (``ai``, LOPR/HOPR
0..100) is refreshed every 50 ms with

    y = 1 + 0.5 exp(-|x - c|^2 / (2 * 10^2)) + N(0, 0.01^2),  c = (5, -5) A,

at the readbacks. Every accepted setpoint put is appended to the put log (JSON lines, the
setpoint before it included), as the caproto test IOC does. Prints ``softioc ready`` once
serving; stops on SIGTERM.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import random
import signal
import sys
import time

from softioc import asyncio_dispatcher, builder, softioc

KNOBS = ["01G-QSS4", "02G-QSS3"]
CENTRE = (5.0, -5.0)
NOISE = 0.01


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--put-log", required=True)
    p.add_argument("--x-init", default="0,0")
    p.add_argument("--limit", type=float, default=15.0)
    args = p.parse_args()
    x0 = [float(v) for v in args.x_init.split(",")]
    rng = random.Random(0)
    dispatcher = asyncio_dispatcher.AsyncioDispatcher()
    builder.SetDeviceName("TEST")  # the loss rate's prefix; knob records are named in full
    readbacks, setpoints = [], []
    current = list(x0)

    def log_put(entry: dict) -> None:
        entry["time"] = time.time()
        with open(args.put_log, "a", encoding="utf-8") as f:
            f.write(json.dumps(entry) + "\n")

    for i, knob in enumerate(KNOBS):

        def on_update(value, i=i, knob=knob):
            log_put({"knob": knob, "value": float(value), "previous": current[i]})
            current[i] = float(value)
            readbacks[i].set(float(value))

        builder.SetDeviceName(knob)
        rb = builder.aIn("Curr1", initial_value=x0[i], PREC=6, EGU="A")
        sp = builder.aOut(
            "CurrSetpt",
            initial_value=x0[i],
            DRVL=-args.limit,
            DRVH=args.limit,
            PREC=6,
            EGU="A",
            always_update=True,
            on_update=on_update,
        )
        readbacks.append(rb)
        setpoints.append(sp)
    builder.SetDeviceName("TEST")
    loss = builder.aIn("BeamLossRate", initial_value=1.0, LOPR=0.0, HOPR=100.0, PREC=5)
    builder.LoadDatabase()
    softioc.iocInit(dispatcher)

    async def refresh():
        while True:
            r2 = sum((current[i] - CENTRE[i]) ** 2 for i in range(len(KNOBS)))
            loss.set(1.0 + 0.5 * math.exp(-r2 / 200.0) + rng.gauss(0.0, NOISE))
            await asyncio.sleep(0.05)

    dispatcher(refresh)
    print("softioc ready", flush=True)
    stop = {"now": False}
    signal.signal(signal.SIGTERM, lambda *a: stop.update(now=True))
    deadline = time.monotonic() + 600.0  # never outlives a test run
    while not stop["now"] and time.monotonic() < deadline:
        time.sleep(0.05)
    return 0


if __name__ == "__main__":
    sys.exit(main())
