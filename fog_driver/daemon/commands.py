"""The service's control commands, as an explicit table: ``COMMANDS`` maps each name to its handler and the
rules its arguments must meet.

The hub answers ``?WATCH``, ``?VERSION`` and ``?AUTH`` itself (``connection.HUB_COMMANDS``) and hands every
other command to ``run_command`` in one of its worker threads.  Each rule reads one argument
(``args.get(name, default)``) and refuses the command with its one-line ERROR when the value does not meet it;
the rules run in order, so the first broken one speaks.  Keys no rule names are ignored.  A handler gets the
service and the values the rules read, and returns the answer (a dict; an ERROR is one too).

=========  ==================================================  =========================================
command    arguments                                           does
=========  ==================================================  =========================================
STATUS     none                                                the STATUS object now
ZERO       none                                                zero the published angles (raw and comp)
BIAS       ``seconds`` (1..86400, default 60)                  capture the residual bias, then remove it
ADAPT      ``enable`` (bool), ``reference_dph``                adapt the weights online, or freeze them
           (+-1e7 deg/h, default 0)
TABLE      ``angle_deg``, ``dwell_s`` (12..86400),              the table has stood at the angle for the
           ``angle_start_deg`` (optional)                      last seconds: adapt from table angles
SAVE       none                                                write the adaptation state file
RELOAD     none                                                load the model file again
=========  ==================================================  =========================================
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import structlog

from ..dwells import number_within, table_angle_deg
from ..errors import FogDriverError
from .acquisition import BiasCapture
from .limits import (
    BIAS_ANSWER_MARGIN_S,
    DEFAULT_BIAS_S,
    MAX_ADAPT_REFERENCE_DPH,
    MAX_BIAS_S,
    MAX_TABLE_ANGLE_DEG,
    MAX_TABLE_DWELL_S,
    MIN_BIAS_S,
    MIN_TABLE_DWELL_S,
)

__all__ = ["COMMANDS", "Arg", "Command", "run_command"]

log = structlog.get_logger("fog_driver.daemon")


@dataclass(frozen=True)
class Arg:
    """One rule on one argument: ``accepts(args.get(name, default))`` or the command is refused with ``message``."""

    name: str
    accepts: Callable[[Any], bool]
    message: str
    default: Any = None


@dataclass(frozen=True)
class Command:
    """A control command: its handler ``handler(service, **values)`` and the rules on its arguments."""

    handler: Callable[..., dict]
    args: tuple[Arg, ...] = ()


def run_command(service: Any, name: str, args: dict) -> dict:
    """``?NAME`` with ``args`` on ``service``: the handler's answer, or the ERROR of an unknown command or of
    the first argument rule broken."""
    command = COMMANDS.get(name)
    if command is None:
        return {"class": "ERROR", "message": f"unknown command ?{name}", "command": name}
    values: dict[str, Any] = {}
    for rule in command.args:
        value = args.get(rule.name, rule.default)
        if not rule.accepts(value):
            return {"class": "ERROR", "message": rule.message}
        values[rule.name] = value
    return command.handler(service, **values)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


# -- the handlers (called from the hub's worker threads) -----------------------------------------------------


def status(service: Any) -> dict:
    with service.lock:
        return service.status_object(mark_cpu=False)


def zero(service: Any) -> dict:
    """Zero the published angles here (the raw capture and the model are untouched)."""
    with service.lock:
        compensator = service.compensator
        if compensator is None:
            return {"class": "ERROR", "message": "no samples yet: nothing to zero"}
        acquisition = service.acquisition
        acquisition.offsets.zero(compensator.angle_raw_arcsec, compensator.angle_comp_arcsec)
        compensator.break_table_chain()  # no table interval is learned across a zero
        service.note("zero")
    return {"class": "ZERO", "zeroed": True}


def bias(service: Any, seconds: float) -> dict:
    """Capture the residual bias over N seconds (device time) of static data, then remove it.

    Answered at once (``BIAS`` ``state: started`` with the capture's ``capture_id``); the result is an event
    published later to every authorized client (the one that asked included, if it is still there):
    ``BIAS`` ``state: done`` with ``bias_dph``, or ``state: failed`` with ``reason`` when the N seconds of
    data did not arrive within N + ``BIAS_ANSWER_MARGIN_S`` seconds of host time (the port went away): the
    capture is then abandoned and the bias in use is kept.  One capture at a time."""
    timeout_s = float(seconds) + BIAS_ANSWER_MARGIN_S
    acquisition = service.acquisition
    with service.lock:
        if acquisition.bias_capture is not None:
            return {"class": "ERROR", "message": "a bias capture is already running"}
        acquisition.bias_captures += 1
        capture = BiasCapture(acquisition.bias_captures, float(seconds))
        timer = threading.Timer(timeout_s, _bias_timed_out, args=(service, capture))
        timer.daemon = True
        capture.timer = timer
        acquisition.bias_capture = capture
        timer.start()
    log.info("bias_started", capture_id=capture.capture_id, seconds=float(seconds))
    return {
        "class": "BIAS",
        "state": "started",
        "capture_id": capture.capture_id,
        "seconds": float(seconds),
        "timeout_s": timeout_s,
    }


def _bias_timed_out(service: Any, capture: BiasCapture) -> None:
    """The timer of a ``?BIAS`` capture: abandon it if it is still the one running (its own thread)."""
    with service.lock:
        if service.acquisition.bias_capture is not capture:
            return  # completed (or replaced) meanwhile
        service.acquisition.bias_capture = None
        event = {
            "class": "BIAS",
            "state": "failed",
            "capture_id": capture.capture_id,
            "seconds": capture.target_s,
            "seconds_captured": capture.seconds,
            "reason": f"only {capture.seconds:.1f} of {capture.target_s:g} s of data arrived within "
            f"{capture.target_s + BIAS_ANSWER_MARGIN_S:g} s (is the instrument sending?); "
            f"the bias in use is kept",
        }
        log.warning("bias_failed", capture_id=capture.capture_id, reason=event["reason"])
        service.publish_event(event)


def adapt(service: Any, enable: bool, reference_dph: float) -> dict:
    """Adapt the model's weights online against ``reference_dph`` (0: the table at rest), or freeze them (which
    also ends adapting from table angles)."""
    with service.lock:
        if service.compensator is None:
            return {"class": "ERROR", "message": "no samples yet: nothing to adapt"}
        if enable and service.compensator.table_engaged:
            return {
                "class": "ERROR",
                "message": "adapting from table angles (?TABLE): a reference rate is the other signal; "
                '?ADAPT={"enable":false} first',
            }
        service.set_reference(float(reference_dph) if enable else None)
    return {"class": "ADAPT", "enable": enable, **({"reference_dph": float(reference_dph)} if enable else {})}


def table(service: Any, angle_deg: float, dwell_s: float, angle_start_deg: float | None) -> dict:
    """The table has stood at ``angle_deg`` for the last ``dwell_s`` seconds (moving from ``angle_start_deg``
    when given): adapt from the table's angles (``compensation.table``).  Refused at once when it cannot be
    a dwell (no samples, shorter than 12 s, longer than the data since a break, out of order, while adapting
    against a reference rate); what the gyro says of it comes once its last block closes (STATUS ``table``)."""
    with service.lock:
        if service.compensator is None:
            return {"class": "ERROR", "message": "no samples yet: no dwell to hold the angle against"}
        try:
            dwell = service.table_dwell(float(angle_deg), float(dwell_s), angle_start_deg)
        except ValueError as exc:
            return {"class": "ERROR", "message": str(exc)}
    return {"class": "TABLE", "angle_deg": float(angle_deg), "t_start_s": dwell.t_start_s, "t_end_s": dwell.t_end_s}


def _angle(v: Any) -> bool:
    """A table angle as every reader of one checks it (``dwells.table_angle_deg``)."""
    try:
        table_angle_deg(v)
    except ValueError:
        return False
    return True


def save(service: Any) -> dict:
    """Write the adaptation state (a snapshot taken under the lock) to the configured file
    (``Service.save_adapt_state``: never over a file that is not an adaptation state; a failure is an ERROR)."""
    path = service.config.adapt_state
    if not path:
        return {"class": "ERROR", "message": "no adapt_state file configured"}
    with service.lock:
        if service.compensator is None:
            return {"class": "ERROR", "message": "no samples yet: nothing to save"}
        doc = service.compensator.adaptation_document()  # a snapshot; written outside the lock
    try:
        service.save_adapt_state(doc)
    except FogDriverError as exc:
        return {"class": "ERROR", "message": str(exc)}
    return {"class": "SAVE", "path": str(path)}


def reload(service: Any) -> dict:
    """Load the model file again; the angles carry on from where they are."""
    try:
        return service.reload_from_file(service.config)
    except FogDriverError as exc:  # keep running with the model in use
        log.error("model_reload_failed", reason=str(exc))
        return {"class": "ERROR", "message": str(exc)}


#: Every control command the service answers: name -> handler and argument rules.
COMMANDS: dict[str, Command] = {
    "STATUS": Command(status),
    "ZERO": Command(zero),
    "BIAS": Command(
        bias,
        (
            Arg(
                "seconds",
                lambda v: _is_number(v) and MIN_BIAS_S <= v <= MAX_BIAS_S,
                f'?BIAS needs "seconds" between {MIN_BIAS_S} and {MAX_BIAS_S}',
                DEFAULT_BIAS_S,
            ),
        ),
    ),
    "ADAPT": Command(
        adapt,
        (
            Arg("enable", lambda v: isinstance(v, bool), '?ADAPT needs "enable": true or false'),
            Arg(
                "reference_dph",
                lambda v: number_within(v, MAX_ADAPT_REFERENCE_DPH),
                f'"reference_dph" must be a number within +-{MAX_ADAPT_REFERENCE_DPH:g} deg/h (0 at rest)',
                0.0,
            ),
        ),
    ),
    "TABLE": Command(
        table,
        (
            Arg("angle_deg", _angle, f'?TABLE needs "angle_deg": a number within +-{MAX_TABLE_ANGLE_DEG:g} degrees'),
            Arg(
                "dwell_s",
                lambda v: _is_number(v) and MIN_TABLE_DWELL_S <= v <= MAX_TABLE_DWELL_S,
                f'?TABLE needs "dwell_s": the seconds the table has stood there, {MIN_TABLE_DWELL_S:g} to '
                f"{MAX_TABLE_DWELL_S:g}",
            ),
            Arg(
                "angle_start_deg",
                lambda v: v is None or _angle(v),
                f'"angle_start_deg" must be a number within +-{MAX_TABLE_ANGLE_DEG:g} degrees',
            ),
        ),
    ),
    "SAVE": Command(save),
    "RELOAD": Command(reload),
}
