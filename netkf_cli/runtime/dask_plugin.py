"""The Dask worker plugin of the local clusters netkf starts (``--executor dask``).

A module of its own because it subclasses ``distributed``'s ``WorkerPlugin``: ``distributed`` is
an optional dependency (the ``netkf[dask]`` extra) that takes seconds to import, so only the Dask
executor (:meth:`netkf_cli.runtime.montecarlo.Execution.client`) imports this module, lazily. Use::

    client.register_plugin(DieWithParentPlugin())
"""

from __future__ import annotations

import os
import signal
import socket
import threading

from distributed.diagnostics.plugin import WorkerPlugin

from netkf_cli.runtime.workers import _alive, start_watchdog


class DieWithParentPlugin(WorkerPlugin):
    """Dask worker plugin: a worker of a ``LocalCluster`` started by netkf exits when the netkf
    process is gone (watchdog only: Dask starts worker processes from helper threads, so
    PR_SET_PDEATHSIG could fire too early), and ignores SIGINT where it runs in the main thread.

    Register with ``client.register_plugin(DieWithParentPlugin())`` (``register_worker_plugin``
    on older ``distributed``). Only meant for local clusters: a remote worker's netkf process is
    not on its machine, so :meth:`setup` does nothing when the pid does not exist locally at
    registration time or the host differs."""

    name = "netkf-die-with-parent"

    def __init__(self, main_pid: int | None = None):
        self.main_pid = os.getpid() if main_pid is None else main_pid
        self.host = socket.gethostname()

    def setup(self, worker) -> None:  # noqa: D401 - Dask API
        if socket.gethostname() != self.host or not _alive(self.main_pid):
            return  # not on the machine of the netkf process (remote cluster): nothing to watch
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        start_watchdog(self.main_pid)
