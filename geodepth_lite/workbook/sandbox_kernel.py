"""The kernel manager nbgrader's executor uses while ``course autograde`` grades a submission: jupyter's,
with the kernel started inside bubblewrap (:func:`geodepth_lite.workbook.sandbox.bwrap_command`). Only nbgrader's
process imports it (``--Execute.kernel_manager_class``), so the package's commands load no jupyter_client."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from jupyter_client.manager import AsyncKernelManager

from geodepth_lite.workbook.sandbox import HIDDEN_ENV, KERNEL_MEMORY_GIB, MEMORY_ENV, SCRATCH_ENV, bwrap_command


class SandboxKernelManager(AsyncKernelManager):
    """jupyter's kernel manager, the kernel started inside bubblewrap and reached over Unix sockets in
    the scratch folder's ``kernel/`` (``$GEODEPTH_SANDBOX_SCRATCH``, made by ``course autograde``), with the
    memory limit ``$GEODEPTH_SANDBOX_MEMORY`` (bytes) that ``course autograde`` passes on."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        scratch = os.environ.get(SCRATCH_ENV)
        if not scratch:
            raise RuntimeError(f"cannot start a sandboxed kernel: ${SCRATCH_ENV} names no scratch folder")
        self._scratch = Path(scratch)
        (self._scratch / "kernel").mkdir(parents=True, exist_ok=True)
        (self._scratch / "work").mkdir(parents=True, exist_ok=True)
        self.transport = "ipc"
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
        hidden = [Path(p) for p in os.environ.get(HIDDEN_ENV, "").split(os.pathsep) if p]
        memory = int(os.environ.get(MEMORY_ENV) or KERNEL_MEMORY_GIB * (1 << 30))
        return bwrap_command(argv, self._scratch, hidden, memory)
