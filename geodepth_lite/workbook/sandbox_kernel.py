"""The kernel manager nbgrader's executor uses while ``course autograde`` grades a submission: jupyter's,
with the kernel started inside bubblewrap (:func:`geodepth_lite.workbook.sandbox.bwrap_command`). Only nbgrader's
process imports it (``--Execute.kernel_manager_class``), so the package's commands load no jupyter_client."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import zmq
from jupyter_client.asynchronous import AsyncKernelClient
from jupyter_client.channels import AsyncZMQSocketChannel
from jupyter_client.manager import AsyncKernelManager
from traitlets import Type

from geodepth_lite.workbook import sandbox
from geodepth_lite.workbook.sandbox import OutputBudget


class BudgetedIOPubChannel(AsyncZMQSocketChannel):
    """The kernel's output channel, each message passed through an :class:`OutputBudget` first: what it
    drops never reaches nbgrader's notebook."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.budget = OutputBudget()

    async def get_msg(self, timeout: float | None = None) -> dict:
        while True:
            kept = self.budget.admit(await super().get_msg(timeout))
            if kept is not None:
                return kept


class BoundedKernelClient(AsyncKernelClient):
    """jupyter's client for the sandboxed kernel: its sockets drop a message part over
    :data:`~geodepth_lite.workbook.sandbox.FRAME_BYTES` unread (zmq's ``MAXMSGSIZE``), and its output
    channel keeps to an :class:`OutputBudget`."""

    iopub_channel_class = Type(BudgetedIOPubChannel)

    def _create_connected_socket(self, channel: str, identity: bytes | None = None):
        self.context.setsockopt(zmq.MAXMSGSIZE, sandbox.FRAME_BYTES)  # a default of the sockets made from now on
        return super()._create_connected_socket(channel, identity)


class SandboxKernelManager(AsyncKernelManager):
    """jupyter's kernel manager, the kernel started inside bubblewrap and reached over Unix sockets in
    the scratch folder's ``kernel/`` (``$GEODEPTH_SANDBOX_SCRATCH``, made by ``course autograde``), with the
    memory limit ``$GEODEPTH_SANDBOX_MEMORY`` (bytes) that ``course autograde`` passes on, and talked to by a
    :class:`BoundedKernelClient`."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        scratch = os.environ.get(sandbox.SCRATCH_ENV)
        if not scratch:
            raise RuntimeError(f"cannot start a sandboxed kernel: ${sandbox.SCRATCH_ENV} names no scratch folder")
        self._scratch = Path(scratch)
        (self._scratch / "kernel").mkdir(parents=True, exist_ok=True)
        (self._scratch / "work").mkdir(parents=True, exist_ok=True)
        self.transport = "ipc"
        self.client_factory = BoundedKernelClient  # what the kernel sends is bounded in this process too
        self.connection_file = str(self._scratch / "kernel" / "connection.json")
        self.ip = str(self._scratch / "kernel" / "socket")

    def format_kernel_cmd(self, extra_arguments: list[str] | None = None) -> list[str]:
        # a signal would reach bwrap, not the kernel: a cell past the timeout is interrupted by a message
        self.kernel_spec.interrupt_mode = "message"
        argv = super().format_kernel_cmd(extra_arguments)
        cwd = (self._launch_args or {}).get("cwd")
        work = self._scratch / "work"
        # the submission's own files, copied: the kernel writes only there. Never a notebook: nbgrader
        # writes the one it executes into that folder first, with the hidden tests put back
        if cwd and Path(cwd).is_dir():
            for item in Path(cwd).iterdir():
                if (item.is_file() and not item.is_symlink() and item.suffix != ".ipynb"
                        and not (work / item.name).exists()):
                    shutil.copyfile(item, work / item.name)
        hidden = [Path(p) for p in os.environ.get(sandbox.HIDDEN_ENV, "").split(os.pathsep) if p]
        memory = int(os.environ.get(sandbox.MEMORY_ENV) or sandbox.KERNEL_MEMORY_BYTES)
        return sandbox.bwrap_command(argv, self._scratch, hidden, memory)
