"""The sharded sweep: same numbers on 1 and on several (simulated) devices."""

import io
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import accel_jax as aj
from accel_jax import _progress
from accel_jax.report import show_progress


def _one(params, gain):
    return aj.scale_factor(params) * gain, aj.damping_ratio(params)


def test_sweep_matches_vmap_single_device():
    mus = jnp.linspace(1e-5, 2e-4, 13)
    batch = eqx.filter_vmap(lambda mu: aj.ServoParams.reference(damping=mu))(mus)
    out = aj.sweep(_one, batch, 2.0, in_axes=(0, None))
    ref = eqx.filter_jit(eqx.filter_vmap(_one, in_axes=(0, None)))(batch, 2.0)
    np.testing.assert_array_equal(out[0], ref[0])
    np.testing.assert_array_equal(out[1], ref[1])
    # A batch of one is run unbatched (a smaller program): the same values and shapes.
    one = jax.tree_util.tree_map(lambda x: x[4:5], batch)
    single = aj.sweep(_one, one, 2.0, in_axes=(0, None))
    assert single[0].shape == (1,) and single[1].shape == (1,)
    np.testing.assert_array_equal(single[0], ref[0][4:5])
    np.testing.assert_array_equal(single[1], ref[1][4:5])


def _first_pair(params, gain):
    return aj.damping_ratio(params) * gain


def test_weak_and_strong_batches_share_one_compilation():
    # A batch whose leaves come from Python numbers is weakly typed; the same batch with one
    # field swept as a float64 array is not. Both must hit one compiled kernel.
    from accel_jax._sweep import _compiled

    ref = aj.ServoParams.reference()
    weak = jax.tree_util.tree_map(lambda x: jnp.full(5, x), ref)  # weak_type leaves
    strong = eqx.tree_at(lambda p: p.damping, weak, jnp.linspace(1e-5, 2e-4, 5, dtype=float))
    assert weak.damping.weak_type and not strong.damping.weak_type
    a = aj.sweep(_first_pair, weak, jnp.asarray(2.0), in_axes=(0, None))
    b = aj.sweep(_first_pair, strong, jnp.asarray(2.0, float), in_axes=(0, None))
    assert _compiled(_first_pair, (0, None))._cached._cache_size() == 1
    np.testing.assert_allclose(a, aj.damping_ratio(ref) * 2.0, rtol=1e-15)
    assert np.all(np.diff(np.asarray(b)) != 0)  # the swept field did reach the kernel


def test_sweep_chunks_and_progress_give_the_same_numbers(capsys, monkeypatch):
    mus = jnp.linspace(1e-5, 2e-4, 13)
    batch = eqx.filter_vmap(lambda mu: aj.ServoParams.reference(damping=mu))(mus)
    whole = aj.sweep(_one, batch, 2.0, in_axes=(0, None))
    for chunk in (1, 4, 13, 100):
        out = aj.sweep(_one, batch, 2.0, in_axes=(0, None), chunk_size=chunk)
        assert out[0].shape == (13,)
        np.testing.assert_array_equal(out[0], whole[0])
        np.testing.assert_array_equal(out[1], whole[1])
    assert "demo sweep" not in capsys.readouterr().err  # silent unless asked
    with show_progress(label="test"):  # asked, but stderr is not a terminal: no bars
        aj.sweep(_one, batch, 2.0, in_axes=(0, None), desc="demo sweep")
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(_progress, "on_terminal", lambda stream=None: True)
    with show_progress(label="test"):
        out = aj.sweep(_one, batch, 2.0, in_axes=(0, None), desc="demo sweep")
    np.testing.assert_array_equal(out[0], whole[0])
    assert "test: demo sweep" in capsys.readouterr().err
    with pytest.raises(ValueError, match="chunk_size"):
        aj.sweep(_one, batch, 2.0, in_axes=(0, None), chunk_size=0)


def test_progress_bars_only_on_a_terminal(tmp_path):
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    closed = io.StringIO()
    closed.close()
    assert _progress.on_terminal(Terminal()) and not _progress.on_terminal(io.StringIO())
    assert not _progress.on_terminal(closed) and not _progress.on_terminal(object())
    # A redirected stderr (a log file) gets no carriage returns or cursor codes.
    log = tmp_path / "log.txt"
    code = textwrap.dedent(
        """
        from accel_jax._progress import bar, show_progress
        with show_progress(label="x"):
            with bar(5, "work") as b:
                for _ in range(5):
                    b.update()
        """
    )
    with log.open("w") as stderr:
        subprocess.run([sys.executable, "-c", code], stderr=stderr, check=True)
    assert log.read_text() == ""


def test_sweep_bad_input():
    with pytest.raises(ValueError, match="disagree on the batch size"):
        aj.sweep(lambda a, b: a + b, jnp.ones(3), jnp.ones(4))
    with pytest.raises(ValueError, match="in_axes entries"):
        aj.sweep(lambda a: a, jnp.ones(3), in_axes=(0, 0))


def test_sweep_on_four_simulated_devices():
    # A fresh interpreter: the device count is fixed when JAX starts.
    code = textwrap.dedent(
        """
        import jax
        jax.config.update("jax_enable_x64", True)
        import equinox as eqx, jax.numpy as jnp, numpy as np
        import accel_jax as aj
        assert jax.device_count() == 4, jax.devices()
        mus = jnp.linspace(1e-5, 2e-4, 13)   # 13: not a multiple of 4, exercises padding
        batch = eqx.filter_vmap(lambda mu: aj.ServoParams.reference(damping=mu))(mus)
        f = lambda p: aj.scale_factor(p) * aj.damping_ratio(p)
        out = aj.sweep(f, batch)
        assert out.shape == (13,)
        one = aj.sweep(f, batch, devices=jax.devices()[:1])
        np.testing.assert_array_equal(np.asarray(out), np.asarray(one))
        chunked = aj.sweep(f, batch, chunk_size=5)   # chunks of 8 on 4 devices, padded
        np.testing.assert_array_equal(np.asarray(chunked), np.asarray(one))
        print("OK", len(out.sharding.device_set))
        """
    )
    from helpers import run_on_simulated_cpu_devices

    proc = run_on_simulated_cpu_devices(code, 4)
    assert proc.returncode == 0, proc.stderr[-3000:]
    # The result lives on all four devices: the batch was really split.
    assert proc.stdout.strip() == "OK 4", proc.stdout


def test_even_chunk_size_splits_into_fewest_equal_chunks():
    from accel_jax._sweep import even_chunk_size

    assert even_chunk_size(18, 16) == 9  # 2 × 9, not 16 + 2 padded to 16
    assert even_chunk_size(16, 16) == 16
    assert even_chunk_size(5, 16) == 5
    assert even_chunk_size(120, 16) == 15  # 8 × 15
    for size in range(1, 200):
        chunk = even_chunk_size(size, 16)
        chunks = -(-size // chunk)
        assert chunk <= 16 and chunks == -(-size // 16)  # as few chunks as possible
        assert chunks * chunk - size < chunks  # less than one padded element per chunk
    with pytest.raises(ValueError, match="must be positive"):
        even_chunk_size(0, 16)


def _compiled_here(caplog, run):
    """`run()`'s result and the XLA compilations of the kernel it logged (not the small
    programs of the slicing and joining around it)."""
    import logging

    caplog.clear()
    with jax.log_compiles(True), caplog.at_level(logging.DEBUG, logger="jax"):
        out = run()
    messages = [r.getMessage() for r in caplog.records]
    return out, [
        m for m in messages
        if "Finished XLA compilation" in m and ("_ahead_kernel" in m or "wrapped" in m)
    ]


def _ahead_kernel(params, gain):
    return aj.damping_ratio(params) * gain + aj.scale_factor(params)


@pytest.mark.parametrize("size", [1, 6])
def test_compile_ahead_leaves_the_sweep_nothing_to_compile(caplog, size):
    # `compile_ahead` compiles the program a sweep of the same shapes runs (a batch of one
    # runs unbatched: another program), from arguments read for their shapes only; the
    # sweep then compiles nothing and gives the values of one that compiled its own.
    from accel_jax._sweep import compile_ahead

    mus = jnp.linspace(1e-5, 2e-4, size)
    batch = eqx.filter_vmap(lambda mu: aj.ServoParams.reference(damping=mu))(mus)
    zeros = jax.tree_util.tree_map(jnp.zeros_like, batch)
    compile_ahead(_ahead_kernel, zeros, jnp.asarray(2.0), in_axes=(0, None), chunk_size=3)
    out, compiled = _compiled_here(
        caplog, lambda: aj.sweep(_ahead_kernel, batch, jnp.asarray(2.0), in_axes=(0, None),
                                 chunk_size=3)
    )  # fmt: skip
    assert compiled == []
    ref = eqx.filter_jit(eqx.filter_vmap(_ahead_kernel, in_axes=(0, None)))(batch, 2.0)
    np.testing.assert_array_equal(out, ref)
    # Another shape is compiled by the sweep itself, as without `compile_ahead`.
    _, compiled = _compiled_here(
        caplog, lambda: aj.sweep(_ahead_kernel, batch, jnp.asarray(2.0), in_axes=(0, None),
                                 chunk_size=2 if size > 1 else 1, desc="other")
    )  # fmt: skip
    assert (compiled != []) == (size > 1)
