"""Instrument emulators: models of the lab's controllers that answer their protocol on a
pseudo-terminal, a TCP socket or in process (``acquisition.emulators.l8121``)."""
