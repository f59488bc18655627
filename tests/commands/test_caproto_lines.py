"""caproto's log records during ``pigp optimize``: one line each, nothing silenced."""

from __future__ import annotations

import io
import logging

from pigp_torch.commands.optimize_output import CAPROTO_LINE_CHARS, caproto_one_line


def test_a_caproto_traceback_is_one_line_and_the_logger_is_put_back():
    """An error logged with its exception (as caproto's circuit logs a protocol error) prints
    one line naming the message and the exception, a warning one line, debug nothing; a long
    message is cut; afterwards the logger is as before."""
    logger = logging.getLogger("caproto.circ")
    parent = logging.getLogger("caproto")
    before = (list(parent.handlers), parent.propagate)
    out = io.StringIO()
    with caproto_one_line(out):
        try:
            raise KeyError(57)
        except KeyError:
            try:
                raise RuntimeError("Unknown Channel ioid 57") from None
            except RuntimeError:
                logger.error("Invalid command %s for VirtualCircuit", "WriteNotifyResponse(...)",
                             exc_info=True)  # fmt: skip
        logger.warning("Removing a circuit due to\n[Errno 104] Connection reset by peer")
        logger.debug("not shown")
        logger.warning("x" * 1000)
    lines = out.getvalue().splitlines()
    assert lines[0] == (
        "caproto error: Invalid command WriteNotifyResponse(...) for VirtualCircuit "
        "(RuntimeError: Unknown Channel ioid 57)"
    )
    assert lines[1] == (
        "caproto warning: Removing a circuit due to [Errno 104] Connection reset by peer"
    )
    assert len(lines) == 3 and len(lines[2]) == CAPROTO_LINE_CHARS and lines[2].endswith("...")
    assert "Traceback" not in out.getvalue()
    assert (list(parent.handlers), parent.propagate) == before
