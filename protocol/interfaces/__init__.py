"""The project's own python-can interfaces (``can.BusABC`` subclasses carrying ``can.Message``):
:mod:`.inproc`, an in-process bus for the simulated-clock bench."""
