"""The process runtime above the library: signals, the guard, real-time mode, process groups.

* ``motorbus.runtime.shutdown``: one shutdown path for every ending (``motorbus.run``,
  ``install_signal_handlers``, the SIGTERM/SIGHUP protection of every open bus,
  deferring Ctrl-C during a safe stop).
* ``motorbus.runtime.guard``: the guard process that sends the leased devices' safe
  frames if the program dies outright (SIGKILL, the OOM killer).
* ``motorbus.runtime.realtime``: SCHED_FIFO, locked memory, the garbage collector.
* ``motorbus.runtime.process_groups``: a bus file's process groups and their CPUs.
* ``motorbus.runtime.hooks``: what the library calls through ``motorbus.lifecycle``.

The library (bus, devices, streams) imports none of this: it calls the hooks of
``motorbus.lifecycle``, which ``motorbus.runtime.hooks`` fills.  ``motorbus``'s package
``__init__`` makes the first bus that opens load it, so every program gets the same
safety whether or not it imports this package.  Importing this package itself loads
nothing (``motorbus.runtime.process_groups`` is read by the bus file at start-up).
"""
