"""A discrete-event simulator that drives the real ``schedule/`` policies on many virtual
nodes in virtual time (``vastray simulate``), with costs measured by ``vastray calibrate``."""
