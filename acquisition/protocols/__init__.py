"""Scripted experiments. ``compression_series``: the paper's darks, flats and compression steps."""

from acquisition.protocols.compression_series import (
    Devices,
    Plan,
    Protocol,
    ProtocolError,
    Result,
    lab_devices,
    load_protocol,
    plan,
    run,
    sim_devices,
)

__all__ = [
    "Protocol",
    "load_protocol",
    "plan",
    "Plan",
    "run",
    "Result",
    "Devices",
    "lab_devices",
    "sim_devices",
    "ProtocolError",
]
