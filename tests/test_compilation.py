"""`persistent_jit`: a stored program computes what `jax.jit` computes, a later process
(here: a second decorated copy, with an empty in-memory cache) loads it instead of tracing
it, the store's edge cases (unreadable file, unexportable function, store off) behave, none
of its failures (missing package, another jax's program, damaged file, unwritable folder)
fails a call, and it composes with jax.jit, jax.vmap and jax.grad."""

import os
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from esther_jax import compilation
from esther_jax.cameras import rig_preset


class Scaled(eqx.Module):
    value: jax.Array
    scale: jax.Array
    label: str = eqx.field(static=True)


def affine(rig, x, offset, *, power: int):
    """A pytree in (a rig, a Module, a Python float), a Module and a tuple out."""
    y = rig.project(x.value) ** power + offset
    return Scaled(y, x.scale * 2.0, x.label + "!"), (jnp.sum(y), power)


def traced(trace_log: list):
    def fun(rig, x, offset, *, power: int):
        trace_log.append(power)
        return affine(rig, x, offset, power=power)

    fun.__module__, fun.__qualname__ = __name__, "affine"  # the store's name, shared by every copy
    return compilation.persistent_jit(fun, static_argnames=("power",))


@pytest.fixture
def store(tmp_path, monkeypatch):
    """A fresh, empty program store for one test (the session's store restored after)."""
    monkeypatch.setattr(compilation, "_store", [tmp_path / compilation.PROGRAMS])
    monkeypatch.setattr(compilation, "_said", set())  # each test sees its own first warnings
    (tmp_path / compilation.PROGRAMS).mkdir()
    return tmp_path / compilation.PROGRAMS


def _inputs():
    rig = rig_preset("esther")
    x = Scaled(jnp.asarray([[0.05, -0.02, 0.4], [0.0, 0.03, 0.5]], jnp.float32), jnp.asarray(1.5, jnp.float32), "hand")
    return rig, x


def test_a_stored_program_equals_jit_and_is_loaded_not_traced(store):
    rig, x = _inputs()
    expected = jax.jit(affine, static_argnames=("power",))(rig, x, 0.25, power=2)

    log_first, log_second = [], []
    first = traced(log_first)(rig, x, 0.25, power=2)
    assert log_first == [2] and len(list(store.glob("*.jaxexport"))) == 1
    second = traced(log_second)(rig, x, 0.25, power=2)  # an empty in-memory cache: from the file
    assert log_second == []
    for out in (first, second):
        assert jax.tree.structure(out) == jax.tree.structure(expected) and out[0].label == "hand!" and out[1][1] == 2
        for got, want in zip(jax.tree.leaves(out), jax.tree.leaves(expected)):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))

    again = traced(log_second)
    again(rig, x, 0.25, power=3)  # another static value: another program
    again(rig, x, 0.25, power=3)  # the same one again: from memory
    again(rig, x, jnp.asarray(0.75, jnp.float32), power=3)  # a strongly typed array for the Python float: the same program
    assert log_second == [3] and len(list(store.glob("*.jaxexport"))) == 2
    with pytest.raises(ValueError, match="label must be a string"):  # the function's own errors come through
        compilation.persistent_jit(_bad)(x)


def _bad(x):
    raise ValueError("label must be a string")


def test_an_unreadable_stored_program_is_traced_again(store):
    rig, x = _inputs()
    traced([])(rig, x, 0.25, power=2)
    (path,) = store.glob("*.jaxexport")
    path.write_bytes(path.read_bytes()[:100])  # truncated
    log = []
    with pytest.warns(compilation.ProgramStoreWarning, match="unreadable stored program"):
        out = traced(log)(rig, x, 0.25, power=2)
    assert log == [2] and np.all(np.isfinite(np.asarray(out[0].value)))
    log = []
    traced(log)(rig, x, 0.25, power=2)  # the file was replaced by a readable one
    assert log == []


def test_a_function_with_a_host_callback_runs_through_jit(store):
    def checked(x):
        return eqx.error_if(x, x < 0, "negative") * 2.0

    with pytest.warns(UserWarning, match="cannot be stored"):
        out = compilation.persistent_jit(checked)(jnp.ones(3))
    np.testing.assert_array_equal(np.asarray(out), 2.0 * np.ones(3))
    assert not list(store.glob("*.jaxexport"))


def test_with_the_store_off_it_is_jax_jit(monkeypatch, tmp_path):
    monkeypatch.setattr(compilation, "_store", [])
    rig, x = _inputs()
    log = []
    out = traced(log)(rig, x, 0.25, power=2)
    expected = jax.jit(affine, static_argnames=("power",))(rig, x, 0.25, power=2)
    assert log == [2] and jax.tree.structure(out) == jax.tree.structure(expected)
    assert not list(tmp_path.rglob("*.jaxexport"))


@pytest.mark.parametrize("stored", [True, False])
def test_compiler_options_reach_the_backend_they_name(stored, monkeypatch, tmp_path):
    """The options of this backend are compiled with (XLA itself names an option it does not
    know, which shows they reach it; it is dropped with that warning), another backend's are
    ignored; store on or off."""
    monkeypatch.setattr(compilation, "_store", [tmp_path] if stored else [])
    x = jnp.linspace(0.0, 1.0, 5)
    here = jax.default_backend()
    quick = compilation.persistent_jit(lambda v: jnp.sin(v) * 2.0, compiler_options=compilation.CPU_QUICK_COMPILE)
    np.testing.assert_allclose(np.asarray(quick(x)), 2.0 * np.sin(np.asarray(x)), rtol=1e-6)
    elsewhere = compilation.persistent_jit(lambda v: v + 1.0, compiler_options={f"not-{here}": {"xla_no_such_option": True}})
    np.testing.assert_array_equal(np.asarray(elsewhere(x)), np.asarray(x) + 1.0)
    made_up = f"xla_no_such_option_{stored}"  # one per case: each set is checked (and warned about) once per process
    unknown = {here: {made_up: True, "xla_backend_optimization_level": 1}}
    with pytest.warns(UserWarning, match=f"does not know the compiler option '{made_up}'"):
        dropped = compilation.persistent_jit(lambda v: v - 1.0, compiler_options=unknown)(x)
    np.testing.assert_array_equal(np.asarray(dropped), np.asarray(x) - 1.0)


def test_two_functions_of_one_name_are_two_programs(store):
    x = jnp.arange(3.0)
    plus, times = compilation.persistent_jit(lambda v: v + 1.0), compilation.persistent_jit(lambda v: v * 3.0)
    np.testing.assert_array_equal(np.asarray(plus(x)), np.arange(3.0) + 1.0)
    np.testing.assert_array_equal(np.asarray(times(x)), np.arange(3.0) * 3.0)
    assert len(list(store.glob("*.jaxexport"))) == 2


def _expected(rig, x, offset=0.25, power=2):
    return jax.jit(affine, static_argnames=("power",))(rig, x, offset, power=power)


def _assert_equal_trees(got, want):
    assert jax.tree.structure(got) == jax.tree.structure(want)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def _store_warnings(record) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, compilation.ProgramStoreWarning)]


def test_without_the_serialisation_package_calls_run_and_it_is_said_once(store, monkeypatch):
    """jax.export's serialisation needs flatbuffers (not a dependency of jax): without it the
    program is traced as without the store, and one warning says so for every program."""

    def missing(*args, **kwargs):
        raise ImportError("Please install 'flatbuffers' in order to use Exported serialization")

    monkeypatch.setattr(jax.export.Exported, "serialize", missing)
    monkeypatch.setattr(jax.export, "deserialize", missing)
    rig, x = _inputs()
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        _assert_equal_trees(traced([])(rig, x, 0.25, power=2), _expected(rig, x))
        _assert_equal_trees(traced([])(rig, x, 0.25, power=3), _expected(rig, x, power=3))  # a second program
    (message,) = _store_warnings(record)
    assert "flatbuffers" in message and "cannot be stored" in message
    assert not list(store.glob("*.jaxexport"))


@pytest.mark.parametrize("failure", ["another jax", "damaged", "garbage"])
def test_a_stored_program_that_cannot_be_loaded_is_traced_again(store, monkeypatch, failure):
    rig, x = _inputs()
    traced([])(rig, x, 0.25, power=2)
    (path,) = store.glob("*.jaxexport")
    if failure == "another jax":  # a program this jax's deserialiser refuses (as another release's would be)
        def refuse(*args, **kwargs):
            raise ValueError("Exported serialization version 99 is not supported")

        monkeypatch.setattr(jax.export, "deserialize", refuse)
    elif failure == "damaged":  # the header and structure intact, the program's bytes not
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2] + bytes(len(data) - len(data) // 2))
    else:
        path.write_bytes(os.urandom(4096))
    log = []
    with pytest.warns(compilation.ProgramStoreWarning, match="tracing again"):
        out = traced(log)(rig, x, 0.25, power=2)
    assert log == [2]
    _assert_equal_trees(out, _expected(rig, x))


def test_an_unwritable_program_folder_never_fails_a_call(tmp_path, monkeypatch):
    """The store's folder cannot be written (here: a file stands where its parent should be,
    which fails for root too): calls compute as without the store, said once."""
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    monkeypatch.setattr(compilation, "_store", [blocker / compilation.PROGRAMS])
    monkeypatch.setattr(compilation, "_said", set())
    rig, x = _inputs()
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        _assert_equal_trees(traced([])(rig, x, 0.25, power=2), _expected(rig, x))
        _assert_equal_trees(traced([])(rig, x, 0.25, power=3), _expected(rig, x, power=3))
    (message,) = _store_warnings(record)
    assert "cannot write stored programs" in message


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_cache_folder_leaves_the_caches_off(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    (folder / compilation.PROGRAMS).mkdir(parents=True)
    for path in (folder / compilation.PROGRAMS, folder):
        path.chmod(0o555)
    _enable_fails_softly(folder, monkeypatch)


def test_a_cache_folder_that_cannot_be_made_leaves_the_caches_off(tmp_path, monkeypatch):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    _enable_fails_softly(blocker / "cache", monkeypatch)


def _enable_fails_softly(folder, monkeypatch):
    monkeypatch.setattr(compilation, "_store", [])
    monkeypatch.setattr(compilation, "_said", set())
    before = jax.config.jax_compilation_cache_dir
    with pytest.warns(compilation.ProgramStoreWarning, match="cannot be written"):
        compilation.enable_compilation_cache(folder)
    assert compilation._store == [] and jax.config.jax_compilation_cache_dir == before
    rig, x = _inputs()
    _assert_equal_trees(traced([])(rig, x, 0.25, power=2), _expected(rig, x))


def test_persistent_jit_composes_with_transformations(store):
    """Inside jax.jit, jax.vmap and jax.grad a persistent_jit function traces through jax.jit
    (a compiled program cannot take tracers); the store is used at the top level only."""
    f = compilation.persistent_jit(lambda v, w: jnp.sin(v) * w, static_argnames=())
    plain = lambda v, w: jnp.sin(v) * w  # noqa: E731
    v, w = jnp.linspace(0.0, 1.0, 4), jnp.asarray(2.0)
    np.testing.assert_allclose(np.asarray(jax.jit(f)(v, w)), np.asarray(plain(v, w)), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.vmap(f, in_axes=(0, None))(v, w)), np.asarray(plain(v, w)), rtol=1e-6)
    grad = jax.grad(lambda v: jnp.sum(f(v, w)))(v)
    np.testing.assert_allclose(np.asarray(grad), np.asarray(2.0 * jnp.cos(v)), rtol=1e-6)
    assert not list(store.glob("*.jaxexport"))  # nothing traced under a transformation is stored
    f(v, w)
    assert len(list(store.glob("*.jaxexport"))) == 1


def test_two_rigs_differing_only_in_name_trace_the_teacher_once(tmp_path):
    """A rig's display name is `rig.json` metadata beside the calibration, not part of the
    traced rig: the teacher's per-rig stages (`prefilter`, `initialise`: triangulation and
    the palm pose in the rig) trace once for two `rig.json` files that differ only in name,
    and compute the same."""
    from esther_jax import mano
    from esther_jax.cameras import StereoRig, rig_name
    from esther_jax.files import write_json

    import fitting

    record = rig_preset("esther").to_dict()
    rigs = [StereoRig.from_json(write_json(tmp_path / f"{name}.json", {**record, "name": name})) for name in ("esther", "another")]
    assert [rig_name(tmp_path / f"{name}.json") for name in ("esther", "another")] == ["esther", "another"]
    model = mano.load_builtin("right")
    dtype = jnp.result_type(float)
    params = mano.ManoParams(jnp.asarray([2.6, 0.2, -0.3], dtype), jnp.zeros((15, 3), dtype), jnp.zeros(10, dtype), jnp.asarray([0.05, 0.1, 0.4], dtype))
    uv = jnp.moveaxis(rigs[0].project(mano.forward_joints(model, params)[None]), 0, 1)  # (1 frame, 2 views, 21, 2)
    box = jnp.concatenate([uv.min(axis=2), uv.max(axis=2)], axis=-1)
    fused = fitting.fuse(uv[None], jnp.ones(uv.shape[:-1], dtype)[None], box[None], jnp.ones(uv.shape[:2], dtype)[None])

    def per_rig(rig, fused, model):
        evidence = fitting.prefilter(rig, fused, fitting.template_bones(model))
        return evidence, fitting.initialise(model, rig, evidence, jnp.zeros(10, dtype))

    stages = eqx.filter_jit(eqx.debug.assert_max_traces(per_rig, max_traces=1))
    first, second = (stages(rig, fused, model) for rig in rigs)
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(second)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_allclose(np.asarray(first[1].transl[0]), np.asarray(params.transl), atol=5e-3)  # a real fit: the wrist
