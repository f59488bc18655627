r"""The test IOC in a subprocess: :func:`start_sim_ioc` (a free port on 127.0.0.1, waits until
the IOC is ready) and its handle :class:`SimIOCProcess`."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from pigp_torch.machines.ring.simulated_epics import (
    DEFAULT_PREFIX,
    FROZEN_SUFFIX,
    GLITCH_READINGS_SUFFIX,
    GLITCH_VALUE_SUFFIX,
    LOSS_RATE_SUFFIX,
    NAN_READINGS_SUFFIX,
    NARROW_KNOB_SUFFIX,
    NARROW_LIMIT_SUFFIX,
    READBACK_DELAY_SUFFIX,
    READBACK_OFFSET_SUFFIX,
    READBACK_SUFFIX,
    REBOOT_ON_READ_SUFFIX,
    SETPOINT_SUFFIX,
    STALL_PUTS_SUFFIX,
    STUCK_KNOB_SUFFIX,
)
from pigp_torch.machines.ring.simulated_epics.ca_env import (
    READY_MESSAGE,
    client_environment,
    free_port,
    patched_environ,
    server_environment,
)


# ----------------------------------------------------------------------------- subprocess helper
@dataclass
class SimIOCProcess:
    """A running simulated IOC subprocess (see :func:`start_sim_ioc`).

    Attributes:
        process: the ``subprocess.Popen`` handle.
        port: its Channel Access port on 127.0.0.1.
        knob_names: the knob names served.
        prefix: prefix of the loss-rate and switch PVs.
        log_path: file receiving the IOC's stdout and stderr.
        put_log_path: the IOC's put log (every setpoint put it accepted, see
            :mod:`~.ioc_pvs`).
    """

    process: subprocess.Popen
    port: int
    knob_names: list[str]
    prefix: str
    log_path: Path
    env: dict[str, str] = field(default_factory=dict)
    put_log_path: Path | None = None

    def puts(self, since: int = 0) -> list[dict]:
        """The entries of the IOC's put log from entry ``since`` on (a torn last line, being
        written, is left out)."""
        if self.put_log_path is None or not self.put_log_path.exists():
            return []
        out = []
        for line in self.put_log_path.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except ValueError:
                break
        return out[since:]

    def n_puts(self) -> int:
        """Entries in the put log so far (a mark for :meth:`puts`)."""
        return len(self.puts())

    @property
    def glitch_readings_pv(self) -> str:
        return f"{self.prefix}{GLITCH_READINGS_SUFFIX}"

    @property
    def glitch_value_pv(self) -> str:
        return f"{self.prefix}{GLITCH_VALUE_SUFFIX}"

    @property
    def stuck_knob_pv(self) -> str:
        return f"{self.prefix}{STUCK_KNOB_SUFFIX}"

    @property
    def readback_offset_pv(self) -> str:
        return f"{self.prefix}{READBACK_OFFSET_SUFFIX}"

    @property
    def narrow_knob_pv(self) -> str:
        return f"{self.prefix}{NARROW_KNOB_SUFFIX}"

    @property
    def narrow_limit_pv(self) -> str:
        return f"{self.prefix}{NARROW_LIMIT_SUFFIX}"

    @property
    def stall_puts_pv(self) -> str:
        return f"{self.prefix}{STALL_PUTS_SUFFIX}"

    @property
    def loss_rate_pv(self) -> str:
        return f"{self.prefix}{LOSS_RATE_SUFFIX}"

    @property
    def nan_readings_pv(self) -> str:
        return f"{self.prefix}{NAN_READINGS_SUFFIX}"

    @property
    def readback_delay_pv(self) -> str:
        return f"{self.prefix}{READBACK_DELAY_SUFFIX}"

    @property
    def frozen_pv(self) -> str:
        return f"{self.prefix}{FROZEN_SUFFIX}"

    @property
    def reboot_on_read_pv(self) -> str:
        return f"{self.prefix}{REBOOT_ON_READ_SUFFIX}"

    @property
    def setpoint_pvs(self) -> list[str]:
        return [f"{n}{SETPOINT_SUFFIX}" for n in self.knob_names]

    @property
    def readback_pvs(self) -> list[str]:
        return [f"{n}{READBACK_SUFFIX}" for n in self.knob_names]

    @property
    def client_env(self) -> dict[str, str]:
        """EPICS client variables that reach this IOC (see :func:`client_environment`)."""
        return client_environment(self.port)

    def alive(self) -> bool:
        return self.process.poll() is None

    def log_tail(self, n_chars: int = 2000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-n_chars:]
        except OSError:
            return ""

    def stop(self, timeout: float = 5.0) -> None:
        """Terminate the IOC (SIGTERM, then SIGKILL after ``timeout`` s); idempotent."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout)

    def kill(self, timeout: float = 5.0) -> None:
        """Kill the IOC at once (SIGKILL): a crash, for fault-injection tests."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout)


def _wait_ready(handle: SimIOCProcess, timeout: float) -> None:
    """Wait for the IOC's ready line, then for its PVs to answer over CA (both bounded)."""
    deadline = time.monotonic() + timeout
    while READY_MESSAGE not in handle.log_tail(100_000):
        if not handle.alive():
            raise RuntimeError(
                f"simulated IOC exited with code {handle.process.returncode}:\n{handle.log_tail()}"
            )
        if time.monotonic() > deadline:
            raise TimeoutError(
                f"simulated IOC not ready after {timeout:.0f} s:\n{handle.log_tail()}"
            )
        time.sleep(0.05)
    from caproto.threading.client import Context

    ctx = Context()
    try:
        names = [handle.loss_rate_pv, handle.readback_pvs[-1]]
        pvs = ctx.get_pvs(*names, timeout=1.0)
        for pv in pvs:
            pv.wait_for_connection(timeout=max(0.5, deadline - time.monotonic()))
            pv.read(timeout=2.0)
    except Exception as err:
        raise TimeoutError(f"simulated IOC PVs did not answer over CA: {err!r}") from err
    finally:
        ctx.disconnect()


@contextlib.contextmanager
def start_sim_ioc(
    seed: int = 1,
    port: int | None = None,
    *,
    knobs="paper13",
    noise: float = 0.04,
    noise_seed: int = 0,
    prefix: str = DEFAULT_PREFIX,
    update_period: float = 0.1,
    readback_delay: float = 0.0,
    set_client_env: bool = True,
    startup_timeout: float = 90.0,
) -> Iterator[SimIOCProcess]:
    r"""Run the simulated IOC in a subprocess on 127.0.0.1 for the ``with`` block.

    Launches ``python -m pigp_torch.machines.ring.simulated_epics.ioc`` with the server bound to the
    loopback interface and ``port`` (default: a free one, so parallel runs do not collide), waits
    (at most ``startup_timeout`` s) for its ready line and for its PVs to answer over CA, and stops
    it (SIGTERM, then SIGKILL) when the block ends, also on errors. The IOC keeps a put log (every
    setpoint put it accepted) in a temporary file, read with :meth:`SimIOCProcess.puts`.

    With ``set_client_env`` (default) the block runs with ``EPICS_CA_ADDR_LIST=127.0.0.1:port``,
    ``EPICS_CA_AUTO_ADDR_LIST=NO`` in ``os.environ`` (restored afterwards), so caproto clients of
    this process — e.g. :class:`~pigp_torch.machine.epics.EpicsMachine` — find this IOC and
    nothing else.

    Yields:
        a :class:`SimIOCProcess` (PV names, port, ``kill()`` for crash tests).

    Raises:
        RuntimeError: the IOC exited during start-up (its log is in the message).
        TimeoutError: it did not answer within ``startup_timeout``.
    """
    from pigp_torch.machines.ring.spear3 import knob_names_for
    from pigp_torch.machines.ring.spec import RingSpec

    names = knob_names_for(knobs)
    ring = RingSpec(knobs=knobs if isinstance(knobs, str) else tuple(names))
    port = free_port() if port is None else int(port)
    cmd = [sys.executable, "-m", f"{__package__}.ioc", "--seed", str(int(seed))]
    cmd += ["--ring", json.dumps(ring.to_dict())]
    cmd += ["--noise", repr(float(noise)), "--noise-seed", str(int(noise_seed))]
    cmd += ["--prefix", prefix, "--port", str(port)]
    cmd += ["--update-period", repr(float(update_period))]
    cmd += ["--readback-delay", repr(float(readback_delay))]
    log_dir = Path(tempfile.mkdtemp(prefix="pigp-sim-ioc-"))
    log_path = log_dir / "ioc.log"
    put_log = log_dir / "puts.jsonl"
    cmd += ["--put-log", str(put_log)]
    env = dict(os.environ)
    env.update(server_environment(port))
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env["PYTHONUNBUFFERED"] = "1"
    with open(log_path, "wb") as log:
        process = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    handle = SimIOCProcess(
        process, port, names, prefix, log_path, env=server_environment(port), put_log_path=put_log
    )
    try:
        env_cm = patched_environ(handle.client_env) if set_client_env else contextlib.nullcontext()
        with env_cm:
            _wait_ready(handle, startup_timeout)
            yield handle
    finally:
        handle.stop()
        with contextlib.suppress(OSError):
            log_path.unlink()
            put_log.unlink(missing_ok=True)
            log_dir.rmdir()
