"""Steering checked against what the session's engine declared (`EngineInfo`).

The protocol's own bounds only keep values finite and small enough to transport; what makes
physical sense depends on the engine (OpenMM with constraints takes 4 fs, a replay has no
temperature). Each refusal names the field and the limit, so the dashboard can say why.
"""

from __future__ import annotations

import protocol as p

SIM_PARAM_FIELDS = ("temperature_K", "timestep_fs", "friction_per_ps", "frame_interval")


def _refuse(message: str, path: str, seq: int | None) -> p.ProtocolError:
    return p.ProtocolError(p.ErrorCode.INVALID_MESSAGE, message, path, seq)


def check_sim_params(engine: p.EngineInfo | None, message: p.SimParams) -> None:
    """Refuse a parameter the engine cannot change or a value outside its range."""
    if engine is None:
        return
    for name in SIM_PARAM_FIELDS:
        value = getattr(message, name)
        if value is None:
            continue
        path = f"sim_params.{name}"
        why = engine.unavailable.get(name)
        if why is not None:
            raise _refuse(f"{engine.name} cannot change {name}: {why}", path, message.seq)
        bounds = engine.params.get(name)
        if bounds is not None and not bounds.min <= value <= bounds.max:
            unit = f" {bounds.unit}" if bounds.unit else ""
            raise _refuse(
                f"{name} {value:g}{unit} is outside {engine.name}'s range "
                f"[{bounds.min:g}, {bounds.max:g}]{unit}",
                path,
                message.seq,
            )


def check_control(engine: p.EngineInfo | None, message: p.Control) -> None:
    """Refuse an action the engine does not offer."""
    if engine is None or not engine.controls or message.action in engine.controls:
        return
    why = engine.unavailable.get(message.action, "not offered by this engine")
    raise _refuse(f"{engine.name} cannot {message.action}: {why}", "control.action", message.seq)


def check_pull(engine: p.EngineInfo | None, message: p.Pull) -> p.Pull:
    """The pull within the engine's limits: refused if the engine takes no forces or the spring
    is stiffer than it allows; the force cap lowered to the engine's."""
    if engine is None or message.release:
        return message
    if engine.pull is None:
        why = engine.unavailable.get("pull", "it takes no external forces")
        raise _refuse(f"{engine.name} cannot be pulled: {why}", "pull", message.seq)
    if message.target is not None and message.spring_k > engine.pull.max_spring_k:
        raise _refuse(
            f"spring_k {message.spring_k:g} kJ/mol/A^2 is stiffer than {engine.name} allows "
            f"({engine.pull.max_spring_k:g})",
            "pull.spring_k",
            message.seq,
        )
    if message.max_force > engine.pull.max_force:
        return message.model_copy(update={"max_force": engine.pull.max_force})
    return message
