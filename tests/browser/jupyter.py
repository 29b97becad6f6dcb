"""A real JupyterLab for the widget's tests and benchmark: `jupyter lab` in a child process on a
loopback port with its own token and folders, its app exposed to the page so a test runs
cells through JupyterLab's own commands."""

from __future__ import annotations

import os
import secrets
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import nbformat

from tests.server.processes import free_port

ROOT = Path(__file__).resolve().parents[2]


def write_notebook(path: Path, cells: list[str]) -> Path:
    """A notebook of code cells, for the Python 3 kernel of this interpreter."""
    book = nbformat.v4.new_notebook()
    book.metadata["kernelspec"] = {
        "name": "python3",
        "display_name": "Python 3",
        "language": "python",
    }
    book.cells = [nbformat.v4.new_code_cell(source) for source in cells]
    nbformat.write(book, path)
    return path


class JupyterLab:
    """`jupyter lab` serving `root`; `stop()` ends it and its kernels."""

    def __init__(self, root: Path, timeout: float = 90.0) -> None:
        self.root = root
        self.port = free_port()
        self.token = secrets.token_hex(16)
        home = root / ".jupyter-home"
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
            "JUPYTER_CONFIG_DIR": str(home / "config"),
            "JUPYTER_RUNTIME_DIR": str(home / "runtime"),
            "JUPYTERLAB_WORKSPACES_DIR": str(home / "workspaces"),
            "IPYTHONDIR": str(home / "ipython"),
            "JUPYTER_PLATFORM_DIRS": "1",
        }
        self.log = root / "jupyterlab.log"
        command = [
            sys.executable, "-m", "jupyter", "lab", "--no-browser",
            "--ip", "127.0.0.1", "--port", str(self.port),
            f"--IdentityProvider.token={self.token}",
            f"--ServerApp.root_dir={root}",
            "--LabApp.expose_app_in_browser=True",
            "--LabApp.news_url=None",
            "--LabApp.check_for_updates_class=jupyterlab.NeverCheckForUpdate",
            "--ServerApp.terminals_enabled=False",
            "--allow-root",  # CI runs as root
        ]  # fmt: skip
        with open(self.log, "ab") as out:
            self.process = subprocess.Popen(
                command, cwd=root, env=env, stdout=out, stderr=subprocess.STDOUT,
                start_new_session=True,
            )  # fmt: skip
        deadline = time.monotonic() + timeout
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"jupyter lab exited: {self.log.read_text()[-2000:]}")
            try:
                answer = httpx.get(
                    f"{self.url}/api/status", params={"token": self.token}, timeout=2
                )
                if answer.status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"jupyter lab did not start: {self.log.read_text()[-2000:]}")
            time.sleep(0.2)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def notebook_url(self, name: str) -> str:
        """The notebook in a workspace of its own (JupyterLab restores a workspace's tabs: a
        notebook opened earlier must not open again beside this one)."""
        workspace = Path(name).stem
        return f"{self.url}/lab/workspaces/{workspace}/tree/{name}?token={self.token}"

    def stop(self) -> None:
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait()


# JupyterLab's own commands, run in the page (the app is exposed as window.jupyterapp)
READY = """() => {
  const app = window.jupyterapp;
  const panel = app && app.shell.currentWidget;
  const kernel = panel && panel.sessionContext && panel.sessionContext.session
    && panel.sessionContext.session.kernel;
  return !!(kernel && kernel.status === 'idle' && panel.content.widgets.length);
}"""
RUN_CELL = """(index) => {
  const app = window.jupyterapp;
  const panel = app.shell.currentWidget;
  panel.content.activeCellIndex = index;
  const asked = performance.now();
  app.commands.execute('notebook:run-cell'); // resolves when the cell has run: not awaited
  return asked;
}"""
RESTART = """async () => {
  const panel = window.jupyterapp.shell.currentWidget;
  await panel.sessionContext.session.kernel.restart();
}"""
KERNEL_IDLE = """() => {
  const k = window.jupyterapp.shell.currentWidget.sessionContext.session.kernel;
  return k.status === 'idle';
}"""


def open_notebook(
    chromium: Any, lab: JupyterLab, name: str, size: tuple[int, int] = (1200, 900)
) -> Any:
    """A page with the notebook open and its kernel idle."""
    context = chromium.new_context(viewport={"width": size[0], "height": size[1]})
    page = context.new_page()
    page.set_default_timeout(120_000)
    page.goto(lab.notebook_url(name))
    page.wait_for_function(READY, timeout=120_000, polling=250)
    return page


def run_cell(page: Any, index: int) -> float:
    """Run cell `index` (returns at once); the page's clock when it was asked to run."""
    started: float = page.evaluate(RUN_CELL, index)
    return started
