"""Compile once per machine, not once per process: the persistent XLA compilation cache,
and the traced programs of `persistent_jit` functions stored beside it.

    import esther_jax
    esther_jax.enable_compilation_cache()   # notebooks, scripts; the `esther` CLI calls it

Programs are stored under `$ESTHER_JAX_CACHE` (default `~/.cache/esther_jax/xla`) and
reused by every later process with the same program, jax version and backend. The XLA
cache saves only the compilation: a new process still traces every function and lowers it
to StableHLO before it can look a program up, which for the teacher's solvers took longer
than loading them (about 11 s against 2 s on a 2-core machine). Functions decorated with
`persistent_jit` (the teacher's programs) therefore also store their lowered program
(`jax.export`, in `programs/`), keyed by this library's source, the decorated function's
code (and its module's source file, for functions outside this library), the versions of
the libraries it traces through, the backend, the arguments' structure, shapes and dtypes
and the static arguments; a later process deserialises it and goes straight to the XLA
cache. Values a function reads from closures or globals are not part of the key: a stored
program keeps the values it was traced with.

XLA's own optimisation costs time too: programs that run once per job can ask for a
cheaper compilation per backend (`persistent_jit(compiler_options=CPU_QUICK_COMPILE)`).
Neither store is ever pruned (a changed library or jax version writes new files beside the
old ones): delete the folder to reclaim its space.

The store never fails a job: a program that cannot be serialised, read or deserialised (a
missing package such as `flatbuffers`, a file of another jax release, a damaged file, a
cache folder that cannot be written) is traced and compiled as it would be without the
store, and a `ProgramStoreWarning` says so once per process and kind of failure. Under a
JAX transformation (a `persistent_jit` function called inside `jax.jit`, `jax.vmap`,
`jax.grad`, ...) the store is not used: the call traces through `jax.jit`, which composes
with every transformation.

JAX never stores a program that contains a host callback (`jax.pure_callback`,
`eqx.error_if`, `jax.debug.print`), and `jax.export` cannot serialise one: the library's
compiled hot paths contain none, and validate their inputs at the edge instead.
"""

import functools
import hashlib
import importlib.metadata
import importlib.util
import inspect
import io
import os
import pathlib
import pickle
import sys
import types
import warnings
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.export
import jax.numpy as jnp

DEFAULT_DIR = pathlib.Path("~/.cache/esther_jax/xla")
PROGRAMS = "programs"
_MAGIC = b"esther-jax program 1\n"
_store: list[pathlib.Path] = []  # the folder of stored programs once enabled (one entry)
_LIBRARY = ("esther_jax", "fitting")  # the packages whose source `_source_digest` covers
_said: set[str] = set()  # the kinds of store failure this process has warned about


class ProgramStoreWarning(UserWarning):
    """The program store (or the XLA cache) could not be used for a program; the job goes on
    without it (compiling in this process as if it were off)."""


def _say_once(kind: str, message: str) -> None:
    """Warn about one kind of store failure once per process."""
    if kind not in _said:
        _said.add(kind)
        warnings.warn(message, ProgramStoreWarning, stacklevel=4)

CPU_QUICK_COMPILE: dict[str, dict[str, Any]] = {"cpu": {"xla_backend_optimization_level": 1, "xla_cpu_use_fusion_emitters": False}}
"""`persistent_jit` options for programs that run once per job (setup, bookkeeping): on the
CPU, LLVM's lighter optimisation level and XLA's loop emitters for fusions instead of its
fusion emitters. Measured on the teacher (2 cores): its once-per-hand programs compile in
about half the time (the shape pooling 6.3 -> 3.2 s); with every program compiled so the
whole teacher ran about 10 % slower, so its solver and pose search do not use them."""

CPU_LIGHT_OPTIMISATION: dict[str, dict[str, Any]] = {"cpu": {"xla_backend_optimization_level": 1}}
"""`persistent_jit` options for hot programs on the CPU: LLVM's lighter optimisation level
only. On the teacher's solver and pose search it saves about a tenth of their
compilation, and their run time is the same within the measurement's noise."""


def enable_compilation_cache(directory: str | os.PathLike | None = None, *, min_compile_time_s: float = 0.0) -> pathlib.Path:
    """Store compiled programs that took longer than `min_compile_time_s` to compile in
    `directory` (default `$ESTHER_JAX_CACHE` or `~/.cache/esther_jax/xla`), and the traced
    programs of `persistent_jit` functions in its `programs/` folder; load both from there
    in later processes. Returns the directory; safe to call more than once. A folder that
    cannot be created or written leaves both caches off, with a `ProgramStoreWarning`.

    The default stores every program, however small: besides its few large solvers the
    teacher runs about thirty small programs (tens of milliseconds each), and a warm
    process loads them faster than it compiles them. The price is more, smaller files in
    the cache (a few hundred per rig and process)."""
    path = pathlib.Path(directory or os.environ.get("ESTHER_JAX_CACHE") or DEFAULT_DIR).expanduser()
    try:
        (path / PROGRAMS).mkdir(parents=True, exist_ok=True)
        probe = path / PROGRAMS / f".write-probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        _store.clear()
        _say_once("folder", f"the compilation cache folder {path} cannot be written ({type(err).__name__}: {err}); "
                            "compiling every program in this process, without the cache (set ESTHER_JAX_CACHE to a writable folder)")  # fmt: skip
        return path
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _store[:] = [path / PROGRAMS]
    return path


def persistent_jit(
    fun: Callable | None = None, *, static_argnames: tuple[str, ...] = (), compiler_options: Mapping[str, Mapping[str, Any]] | None = None
) -> Callable:
    """`jax.jit`, whose lowered program is also stored once `enable_compilation_cache` has
    been called (before that it is exactly `jax.jit(fun, static_argnames=...,
    compiler_options=...)` with this backend's options). Called inside another
    transformation (`jax.jit`, `jax.vmap`, `jax.grad`, ...) it is `jax.jit(fun,
    static_argnames=...)`, which composes with all of them (XLA options are the outermost
    program's business there), and nothing is stored.

    `compiler_options` maps a backend's platform name (`"cpu"`, `"gpu"`, ...) to the XLA
    options its programs are compiled with (`jax.jit`'s `compiler_options`), read when a
    program is first compiled: e.g. `CPU_QUICK_COMPILE` for programs that run once per job,
    whose compilation would cost more than their run. Options the installed XLA does not
    know are dropped with a warning.

    With the store enabled, each new combination of the arguments' pytree structure, their
    shapes and dtypes and the static arguments' values is traced and exported once per
    machine (`jax.export`), compiled ahead of time (through the XLA cache) and kept in
    memory for the process; a later process loads the program instead of tracing it.
    Differences from `jax.jit` there: arguments are taken at their dtypes as strongly
    typed arrays (a Python float is a float32 or float64 array, as `jnp.asarray` makes it),
    they must live on the default device, and `fun` must contain no host callback (a
    function that cannot be exported runs through `jax.jit`, with a warning naming it)."""
    if fun is None:
        return functools.partial(persistent_jit, static_argnames=static_argnames, compiler_options=compiler_options)
    options_by_platform = dict(compiler_options or {})

    def options_here() -> dict | None:  # at a call: asking for the backend at import would initialise it
        return _known_options(tuple(sorted(options_by_platform.get(jax.default_backend(), {}).items())))

    @functools.cache
    def jitted():
        return jax.jit(fun, static_argnames=static_argnames, compiler_options=options_here())

    @functools.cache
    def nested():  # inside another transformation: XLA options belong to the outermost jit
        return jax.jit(fun, static_argnames=static_argnames)

    signature = inspect.signature(fun)
    name = f"{fun.__module__}.{fun.__qualname__}"
    code = functools.cache(lambda: _code_digest(fun))  # at the first stored call, not at import
    programs: dict = {}  # (treedef, static, avals) -> (compiled, output treedef)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((args, kwargs))):
            return nested()(*args, **kwargs)  # under jit, vmap, grad, ...: traced through, never stored
        if not _store:
            return jitted()(*args, **kwargs)
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        static = tuple((k, bound.arguments[k]) for k in static_argnames)
        leaves, treedef = jax.tree.flatten({k: v for k, v in bound.arguments.items() if k not in static_argnames})
        leaves = [x if isinstance(x, jax.Array) and not x.weak_type else jnp.asarray(x, jnp.result_type(x)) for x in leaves]
        avals = tuple((x.shape, x.dtype) for x in leaves)
        key = (treedef, static, avals)
        if key not in programs:
            programs[key] = _program(fun, signature, name, code(), treedef, static, avals, options_here())
        compiled, out_treedef = programs[key]
        if compiled is None:  # not exportable, or the store failed: jax.jit's program (warned about once)
            return jitted()(*args, **kwargs)
        return jax.tree.unflatten(out_treedef, compiled(*leaves))

    return call


def _program(fun: Callable, signature: inspect.Signature, name: str, code: str, treedef, static: tuple, avals: tuple, options: dict | None):
    """The compiled program (XLA `options`) and output structure of `fun` at one
    signature: loaded from the store, or traced, exported and stored. The stored program
    does not depend on the options: they are part of the XLA cache's key."""
    key = hashlib.sha256()
    config = (jax.default_backend(), jax.config.jax_enable_x64, jax.config.jax_default_matmul_precision)
    for part in (_source_digest(), code, config, name, str(treedef), repr(static), repr(avals)):
        key.update(repr(part).encode() + b"\0")
    path = _store[0] / f"{name}-{key.hexdigest()[:40]}.jaxexport"
    shapes = [jax.ShapeDtypeStruct(shape, dtype) for shape, dtype in avals]
    loaded = _load(path, packages=(*_LIBRARY, fun.__module__.split(".")[0]))
    if loaded is not None:
        exported, out_treedef = loaded
    else:
        structure = []

        @functools.wraps(fun)
        def flat(*leaves):
            arguments = jax.tree.unflatten(treedef, leaves) | dict(static)
            bound = inspect.BoundArguments(signature, {p: arguments[p] for p in signature.parameters})
            leaves_out, out_treedef = jax.tree.flatten(fun(*bound.args, **bound.kwargs))
            structure.append(out_treedef)
            return leaves_out

        try:
            exported = jax.export.export(jax.jit(flat))(*shapes)
        except Exception as err:
            if not structure:  # the function's own error, raised while tracing it
                raise
            # traced, but not exportable: a host callback, a custom call without a stable serialisation
            warnings.warn(f"{name} cannot be stored as a program ({str(err).splitlines()[0]}); it runs through jax.jit in every process", stacklevel=3)
            return None, None
        out_treedef = structure[0]
        _save(path, exported, jax.tree.unflatten(out_treedef, list(range(out_treedef.num_leaves))))
    run = functools.wraps(fun)(lambda *leaves: exported.call(*leaves))
    try:
        return jax.jit(run).lower(*shapes).compile(compiler_options=options), out_treedef
    except Exception as err:  # noqa: BLE001 - e.g. a stored program this jax cannot run: jax.jit's own
        _say_once("compile", f"the stored program {path.name} cannot be compiled ({type(err).__name__}: {str(err).splitlines()[0]}); "
                             "compiling such programs with jax.jit in this process")  # fmt: skip
        return None, None


@functools.cache
def _known_options(items: tuple) -> dict | None:
    """The XLA options `items` (sorted (name, value) pairs) less those this XLA release does
    not know, which are dropped with a warning: they only cheapen compilation, and XLA's
    option names change between releases. Checked once per set on a trivial program."""
    options = dict(items)
    while options:
        try:
            jax.jit(lambda x: x).lower(jnp.zeros(())).compile(compiler_options=options)
            return options
        except RuntimeError as err:  # XLA: "INVALID_ARGUMENT: No such compile option: 'name'"
            unknown = [k for k in options if f"'{k}'" in str(err)]
            if "No such compile option" not in str(err) or not unknown:
                raise
            warnings.warn(f"this XLA does not know the compiler option {unknown[0]!r}; compiling without it", stacklevel=4)
            del options[unknown[0]]
    return None


def _save(path: pathlib.Path, exported, skeleton) -> None:
    """One file: a header, the output structure (the output pytree with its leaves
    numbered; plain pickle of this library's modules) and the serialised program."""
    from .files import atomic_output

    try:
        structure = pickle.dumps(skeleton, protocol=pickle.HIGHEST_PROTOCOL)
        program = bytes(exported.serialize())  # needs the flatbuffers package
    except Exception as err:  # noqa: BLE001 - an unstorable program is only traced again by the next process
        _say_once(_failure_kind(err), f"programs cannot be stored ({type(err).__name__}: {err}); every process traces them "
                                      "again (the XLA cache still keeps their compilation)")  # fmt: skip
        return
    try:
        with atomic_output(path) as tmp:
            tmp.write_bytes(_MAGIC + len(structure).to_bytes(8, "little") + structure + program)
    except OSError as err:
        _say_once("write", f"cannot write stored programs to {path.parent} ({type(err).__name__}: {err}); "
                           "every process traces them again")  # fmt: skip


def _failure_kind(err: Exception) -> str:
    """The kind of a store failure `_say_once` reports once: a missing package (both when
    storing and loading), or anything else about one file."""
    return "package" if isinstance(err, ImportError) else "damaged"


def _load(path: pathlib.Path, packages: tuple[str, ...]):
    """(exported, output treedef) from a stored program, or None when there is none or it
    cannot be read (then it is traced again and the file replaced). The output structure
    may name classes of `packages` only."""
    try:
        data = path.read_bytes()
    except (FileNotFoundError, NotADirectoryError):  # none stored (yet)
        return None
    except OSError as err:
        _say_once("read", f"cannot read stored programs such as {path} ({type(err).__name__}: {err}); tracing them again")
        return None
    try:
        if not data.startswith(_MAGIC):
            raise ValueError("not a stored program")
        start = len(_MAGIC) + 8
        end = start + int.from_bytes(data[len(_MAGIC):start], "little")
        skeleton = _Unpickler(io.BytesIO(data[start:end]), packages).load()
        return jax.export.deserialize(bytearray(data[end:])), jax.tree.structure(skeleton)
    except Exception as err:  # noqa: BLE001 - any unreadable file is traced again (and replaced)
        kind = _failure_kind(err)
        what = "stored programs cannot be read" if kind == "package" else f"ignoring the unreadable stored program {path}"
        _say_once(kind, f"{what} ({type(err).__name__}: {err}); tracing again (later such files are not reported)")
        return None


class _Unpickler(pickle.Unpickler):
    """Reads a stored output structure: classes of the given packages (this library's and
    the decorated function's) and plain containers, never arbitrary callables."""

    BUILTINS = frozenset({"tuple", "list", "dict", "set", "frozenset", "int", "float", "complex", "bool", "str", "bytes", "slice"})

    def __init__(self, file, packages: tuple[str, ...]):
        super().__init__(file)
        self.packages = packages

    def find_class(self, module, name):
        if module.split(".")[0] in self.packages or (module == "builtins" and name in self.BUILTINS):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"a stored program's output structure names {module}.{name}, which it may not")


@functools.cache
def _source_digest() -> str:
    """What a stored program depends on besides its arguments: this library's source (read
    once, at the first stored call: files edited later in the process's life cannot key
    programs traced from the code it runs) and the versions of the libraries it traces
    through."""
    h = hashlib.sha256()
    for package in _LIBRARY:
        root = pathlib.Path(importlib.util.find_spec(package).origin).parent  # found, not imported
        for path in sorted(root.rglob("*.py")):
            h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    for dist in ("jax", "jaxlib", "equinox", "optimistix", "lineax"):
        h.update(f"{dist}={importlib.metadata.version(dist)}\0".encode())
    return h.hexdigest()



def _code_digest(fun: Callable) -> str:
    """The decorated function's own part of its programs' key: its code object (two
    functions of one name, lambdas say, are two programs) and, for a function defined
    outside this library (whose source `_source_digest` covers), its module's source file as it
    was when the function was decorated. Values the function reads from closures or
    globals, and code in other modules it calls, are not part of the key."""
    h = hashlib.sha256()
    code = getattr(inspect.unwrap(fun), "__code__", None)
    for part in _code_parts(code) if code is not None else [repr(type(fun))]:
        h.update(part.encode() if isinstance(part, str) else part)
    module = sys.modules.get(fun.__module__)
    file = getattr(module, "__file__", None)
    if file and fun.__module__.split(".")[0] not in _LIBRARY:
        try:
            h.update(pathlib.Path(file).read_bytes())
        except OSError:  # a module without a readable source file: its code object alone
            pass
    return h.hexdigest()


def _code_parts(code: types.CodeType):
    """A code object's bytecode, names and constants, nested code included, in a form that
    is the same in every process (unlike `marshal`'s, which depends on reference counts)."""
    yield code.co_code
    yield repr((code.co_names, code.co_varnames, code.co_freevars))
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            yield from _code_parts(const)
        else:
            yield repr(sorted(map(repr, const))) if isinstance(const, frozenset) else repr(const)
