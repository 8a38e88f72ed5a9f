"""Reports and study plumbing: the HTML report the CLI's `report` writes, the command line
and run rules every study script shares, what the `accel-jax` commands share on theirs
(`_command`), what they print (`text`) and draw (`figures`), and the atomic file writers
with provenance."""

from .._io import provenance as provenance
from .._io import save_figure_atomic as save_figure_atomic
from .._io import write_json_atomic as write_json_atomic
from .._progress import show_progress as show_progress
from ._study import Figures as Figures
from .figures.identification import identification_figure as identification_figure
from ._study import study_main as study_main
from ._study import study_run as study_run
from .text.identification import identification_summary as identification_summary
