"""The README's API example runs as printed (so the first code a user copies cannot rot)."""

import re
from pathlib import Path

README = Path(__file__).resolve().parent.parent / "README.md"


def test_readme_api_example_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "the README lost its API example"
    namespace = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    est, p = namespace["est"], namespace["p"]
    import accel_jax as aj

    assert abs(float(aj.relative_error_percent(est.scale_factor, aj.scale_factor(p)))) < 0.5
    assert 60e-6 < float(namespace["vib"]) < 70e-6  # 64.6 ppm of g at 1 g, 2 g sine (docs/models.md §3)
    assert "verdict: gauss_markov" in capsys.readouterr().out
