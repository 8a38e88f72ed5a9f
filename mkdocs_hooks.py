"""mkdocs hooks (mkdocs.yml `hooks:`) that serve the notebooks to the mkdocs-jupyter plugin.

The plugin renders each `notebooks/*.py` (a jupytext percent script) as a page and, with
`execute: true`, runs it in a Jupyter kernel first. Two things it does not do are done here:

- The notebooks live in `notebooks/`, outside `docs_dir`: `on_files` adds each one to the
  site as the page `notebooks/<name>.py` (the file itself, not a copy), before the plugin's
  own `on_files` picks up the pages it renders.
- The plugin starts the kernel in mkdocs' working folder (the repository, with `make docs`),
  so a file a notebook writes (`design_tolerance.png`, ...) would land in the working tree:
  `on_pre_page` makes each notebook's render, execution included, run from a new temporary
  folder that is deleted afterwards. There the kernel also keeps its IPython and Jupyter
  folders (nothing is written to, or read from, ~/.ipython, ~/.jupyter or ~/.local/share/
  jupyter; the kernel named in mkdocs.yml is found in the virtual environment), and matplotlib
  uses its inline backend, the kernel's default, which puts each figure in the page as a PNG,
  even where the caller set MPLBACKEND (e.g. to Agg, which would show none).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parent
NOTEBOOKS = "notebooks"
INLINE_BACKEND = "module://matplotlib_inline.backend_inline"


def _is_notebook(file):
    return file.src_uri.startswith(f"{NOTEBOOKS}/") and file.src_uri.endswith(".py")


@event_priority(50)  # before mkdocs-jupyter's on_files (priority 0) wraps the pages it renders
def on_files(files, config):
    for path in sorted((ROOT / NOTEBOOKS).glob("*.py")):
        files.append(
            File(
                f"{NOTEBOOKS}/{path.name}",
                src_dir=str(ROOT),
                dest_dir=config.site_dir,
                use_directory_urls=config.use_directory_urls,
            )
        )
    return files


@event_priority(-50)  # after mkdocs-jupyter's on_pre_page replaced page.render
def on_pre_page(page, config, files):
    if not _is_notebook(page.file):
        return page
    render = page.render

    def render_in_scratch_folder(config, files):
        with _scratch_folder():
            render(config, files)

    page.render = render_in_scratch_folder
    return page


@contextlib.contextmanager
def _scratch_folder():
    """Work in a new temporary folder, deleted afterwards, with the kernel's settings there."""
    with tempfile.TemporaryDirectory(prefix="accel_jax-notebook-") as scratch:
        jupyter_config = Path(scratch, ".jupyter")
        jupyter_config.mkdir()
        # Encrypt the kernel's local TCP traffic (CurveZMQ: ipykernel's kernelspec declares it
        # and pyzmq's wheels carry it), rather than have the kernel warn of plain text.
        (jupyter_config / "jupyter_nbconvert_config.json").write_text(
            json.dumps({"KernelManager": {"transport_encryption": "auto"}})
        )
        environment = {
            "MPLBACKEND": INLINE_BACKEND,
            "IPYTHONDIR": os.path.join(scratch, ".ipython"),
            "JUPYTER_CONFIG_DIR": str(jupyter_config),
            "JUPYTER_DATA_DIR": os.path.join(scratch, ".jupyter-data"),
            "JUPYTER_RUNTIME_DIR": os.path.join(scratch, ".jupyter-runtime"),
        }
        with _working_folder(scratch), _environment(environment):
            yield


@contextlib.contextmanager
def _working_folder(path):
    before = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(before)


@contextlib.contextmanager
def _environment(variables):
    """Set environment variables (the kernel inherits this process's), then restore them."""
    before = {name: os.environ.get(name) for name in variables}
    os.environ.update(variables)
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
