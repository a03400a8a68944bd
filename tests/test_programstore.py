"""The store of traced engine programs (`eant2_jax.programs.store`): a run computes the same
with the store off, cold and warm; a warm store skips tracing; anything that shapes the
program keys it; bad, planted or foreign entries are never used, a folder others may write
is refused, and unwritable folders cost nothing but the saving (issue 40: data, not code)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pickle
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import eant2_jax
from eant2_jax import EANT2Config, ExploitConfig, exploitation, tasks
from eant2_jax.programs import store as programstore

CONFIG = EANT2Config(population=4, exploit=ExploitConfig(max_iters=40, pruner="covariance"))
WALL = eant2_jax.loop.RUN_DEPENDENT


@pytest.fixture(scope="module", autouse=True)
def xla_cache(tmp_path_factory):
    """JAX's compilation cache on, in a folder of this module, as the store is used (the store
    follows it: `test_the_store_follows_the_compilation_cache`). What these tests study is
    the store's tracing and its entries; the same program's XLA compilation, from a stored
    entry or the one traced again over a damaged one, is read back instead of compiled
    again (about 3 s each). The store's own folder is each test's (`store`)."""
    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
    before = [getattr(jax.config, name) for name in names]
    jax.config.update(names[0], str(tmp_path_factory.mktemp("xla")))
    jax.config.update(names[1], 1.0)  # the engine's programs, not the small ones
    yield
    for name, value in zip(names, before, strict=True):
        jax.config.update(name, value)


def fresh_store(mp: pytest.MonkeyPatch, folder):
    """The store in ``folder``, with this process's programs forgotten (a new process)."""
    mp.setattr(programstore, "directory", lambda: folder)
    mp.setattr(programstore, "_PROGRAMS", {})
    mp.setattr(programstore, "_FAILED", [])
    return folder


@pytest.fixture
def store(tmp_path, monkeypatch):
    """The store in a fresh folder, with this process's programs forgotten (a new process)."""
    return fresh_store(monkeypatch, tmp_path / "programs")


@pytest.fixture(scope="module")
def stored_run(tmp_path_factory):
    """``_run(generations=0)`` with the store cold, once for the module: what it computed,
    and the name and bytes of the one entry it stored. The tests that start from "a run
    stored its program" put that entry into their own store instead of running again (a
    run is about 3 s here, nearly all of it compiling the program)."""
    folder = tmp_path_factory.mktemp("stored") / "programs"
    with pytest.MonkeyPatch.context() as mp:
        fresh_store(mp, folder)
        first = _run(generations=0)
    (path,) = folder.glob("*.program")
    return first, path.name, path.read_bytes()


def _forget(monkeypatch):
    """As a new process: no program of the store in memory."""
    monkeypatch.setattr(programstore, "_PROGRAMS", {})


# Servo's start poses cut to a few: its program is what these tests store and compare, and the
# number of starts is a data size, not part of the program's form.
TASK_OPTIONS = {"xor": {}, "servo": {"n_starts": 4}}


def _run(task="xor", config=CONFIG, generations=1):
    result = eant2_jax.run(tasks.make(task, **TASK_OPTIONS[task]), key=jax.random.key(7),
                           config=config, generations=generations)  # fmt: skip
    records = [
        json.dumps({k: v for k, v in r.to_json().items() if k not in WALL}, sort_keys=True)
        for r in [*result.generations, *result.pruning]
    ]
    return str(result.best), records


def _no_tracing(monkeypatch):
    """Make tracing a program for the store fail loudly."""

    def refuse(*args, **kwargs):
        raise AssertionError("the store traced a program it holds")

    monkeypatch.setattr(programstore.export, "export", refuse)


@pytest.mark.slow
@pytest.mark.parametrize("task", ["xor", "servo"])
def test_off_cold_and_warm_store_give_the_same_run(store, monkeypatch, task, stored_run):
    """A run with the store off, cold (it traces and stores its programs) and warm (it reads
    them, tracing nothing) computes the same. XOR's cold run is the module's `stored_run`
    (the same run, its entry put into this test's store); servo's is run here, another
    task's program, without a pruner (XOR's program has the pruner's parts)."""
    small = dataclasses.replace(CONFIG, exploit=CONFIG.exploit.replace(max_iters=6, pruner="none"))
    config = CONFIG if task == "xor" else small
    monkeypatch.setattr(programstore, "directory", lambda: None)
    off = _run(task, config, generations=0)
    monkeypatch.setattr(programstore, "directory", lambda: store)
    if task == "xor":
        cold, name, entry = stored_run
        store.mkdir(parents=True, mode=0o700)  # as the store makes it
        (store / name).write_bytes(entry)
    else:
        cold = _run(task, config, generations=0)
    files = sorted(store.glob("*.program"))
    assert files, "nothing stored"
    _forget(monkeypatch)
    _no_tracing(monkeypatch)
    warm = _run(task, config, generations=0)
    assert off == cold == warm
    assert sorted(store.glob("*.program")) == files  # read, not written again


def chunk_args(task_name: str, config: ExploitConfig, *, run_bucket: bool = False):
    """``(task, args)``: the engine chunk's arguments for one minimal structure (4 rows);
    with ``run_bucket``, in the bucket a run gives its generation 0 (`grow_bucket`)."""
    from eant2_jax import tuning
    from eant2_jax.exploration import initial_genome
    from eant2_jax.loop import grow_bucket

    task = tasks.make(task_name)
    genome = initial_genome(np.random.default_rng(1), task.n_inputs, task.n_outputs)
    bucket = grow_bucket([genome], None) if run_bucket else None
    init_key, run_key = jax.random.split(jax.random.key(2))
    prep = tuning.prepare([genome], task, key=init_key, config=config, min_rows=4, bucket=bucket)
    args = (*exploitation.placed(prep.state, prep.batch.layout, prep.tables, task, None),
            run_key, config)  # fmt: skip
    return task, args


@pytest.mark.slow
def test_the_engine_state_is_equal_to_the_last_bit(store):
    """One chunk of the engine: the stored program's outputs equal jit's, every leaf. (XOR's
    chunk, with the covariance pruner: a small program; a servo run computes the same with
    the store off, cold and warm, `test_off_cold_and_warm_store_give_the_same_run`.) The
    chunk of `_run`'s generation 0, in its bucket and length: where the module's runs went
    first, JAX's compilation cache holds both programs' XLA compilations."""
    task, args = chunk_args("xor", CONFIG.exploit, run_bucket=True)
    static = {"length": CONFIG.exploit.chunk}
    stored = programstore.lookup(exploitation.run_chunk, args, static, task=task)
    assert stored is not None
    plain = exploitation.run_chunk(*args, **static)
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(stored(*args)), strict=True):
        if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key):
            a, b = jax.random.key_data(a), jax.random.key_data(b)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def _keys(folder) -> set[str]:
    return {p.name for p in folder.glob("*.program")}


def _store_chunk(config: ExploitConfig) -> None:
    """Store (trace, not compile) the engine's chunk for one XOR structure under ``config``."""
    task, args = chunk_args("xor", config)
    assert programstore.lookup(exploitation.run_chunk, args, {"length": 5}, task=task)


@pytest.mark.slow
def test_what_shapes_the_program_keys_it(store, monkeypatch):
    _store_chunk(CONFIG.exploit)
    assert len(_keys(store)) == 1
    _forget(monkeypatch)
    _store_chunk(CONFIG.exploit)  # the same program: read, not stored again
    assert len(_keys(store)) == 1
    # Where JAX caches and logs compiled programs is not what a program is: a moved cache
    # folder, another cache threshold or compile logging still read the same entry.
    settings = {
        "jax_compilation_cache_dir": str(store.parent / "moved"),
        "jax_persistent_cache_min_compile_time_secs": 0.0,
        "jax_log_compiles": True,
    }
    before = {name: getattr(jax.config, name) for name in settings}
    trace = programstore.export.export
    try:
        for name, value in settings.items():
            jax.config.update(name, value)
        _forget(monkeypatch)
        _no_tracing(monkeypatch)
        _store_chunk(CONFIG.exploit)
    finally:
        for name, value in before.items():
            jax.config.update(name, value)
    monkeypatch.setattr(programstore.export, "export", trace)
    assert len(_keys(store)) == 1
    # Another static setting of the engine: another program.
    _store_chunk(CONFIG.exploit.replace(pruner="none"))
    assert len(_keys(store)) == 2
    # Changed code of this package (or another JAX): another key, never the old program.
    monkeypatch.setattr(programstore, "code_digest", lambda: b"other source")
    _forget(monkeypatch)
    _store_chunk(CONFIG.exploit)
    assert len(_keys(store)) == 3
    # JAX's configuration is part of the key.
    monkeypatch.setattr(programstore, "_config_digest", lambda: b"other config")
    _forget(monkeypatch)
    _store_chunk(CONFIG.exploit)
    assert len(_keys(store)) == 4


def test_the_code_digest_covers_every_module_of_the_package(monkeypatch, tmp_path):
    """Both folders of a source checkout (eant2_jax/ and kernels/) count: an edit to a kernel
    gives another digest."""
    from eant2_jax import kernels

    programstore.code_digest.cache_clear()  # the tree may have changed since it was cached
    digest = programstore.code_digest()
    assert isinstance(digest, bytes) and len(digest) == 32
    copy = tmp_path / "kernels"
    copy.mkdir()
    for f in Path(kernels.__path__[0]).glob("*.py"):
        (copy / f.name).write_bytes(f.read_bytes())
    monkeypatch.setattr(kernels, "__path__", [str(copy)])
    programstore.code_digest.cache_clear()
    try:
        assert programstore.code_digest() == digest
        (copy / "cmaes.py").write_text((copy / "cmaes.py").read_text() + "\n# edited\n")
        programstore.code_digest.cache_clear()
        assert programstore.code_digest() != digest
    finally:
        programstore.code_digest.cache_clear()


def _entry(path: Path) -> tuple[dict, bytes]:
    head, _, payload = path.read_bytes().partition(b"\n")
    return json.loads(head), payload


def _whole(path: Path) -> bool:
    """An entry of its own key whose bytes match its manifest (what a writer leaves)."""
    manifest, payload = _entry(path)
    return (
        manifest["key"] == path.stem and manifest["sha256"] == hashlib.sha256(payload).hexdigest()
    )


def _stored_leaves():
    """The entry's key and the arguments' leaves of `_run`'s generation 0 program."""
    task, args = chunk_args("xor", CONFIG.exploit)
    return jax.tree.leaves(args)


@pytest.mark.slow
def test_an_entry_is_a_manifest_and_bytes(store):
    """One line of strict JSON naming the key, versions and the bytes' hash, then the
    bytes `jax.export` wrote; no pickle anywhere in the entry."""
    _store_chunk(CONFIG.exploit)
    (path,) = store.glob("*.program")
    manifest, payload = _entry(path)
    assert manifest["key"] == path.stem and manifest["format"] == programstore.FORMAT
    assert manifest["jax"] == jax.__version__ and manifest["bytes"] == len(payload)
    assert manifest["sha256"] == hashlib.sha256(payload).hexdigest()
    assert len(manifest["out_avals"]) > 0 and manifest["out_tree"].startswith("PyTreeDef")
    assert "import pickle" not in Path(programstore.__file__).read_text()


def _damaged(good: bytes) -> list[tuple[str, bytes]]:
    head, _, payload = good.partition(b"\n")
    manifest = json.loads(head)
    flipped = bytearray(good)
    flipped[len(head) + 1 + len(payload) // 2] ^= 0x01  # one bit of the program's bytes
    other = dict(manifest, jax="0.0.1")
    return [
        ("empty", b""),
        ("not an entry", b"not an entry"),
        ("a flipped bit", bytes(flipped)),
        ("a partial write", good[: len(good) // 2]),
        ("another version", json.dumps(other).encode() + b"\n" + payload),
        ("non-strict JSON", head.replace(b'"bytes"', b'"nan": NaN, "bytes"') + b"\n" + payload),
    ]


def _new_entry(store, before: set) -> Path:
    (path,) = set(store.glob("*.program")) - before
    return path


@pytest.mark.slow
def test_a_damaged_entry_is_traced_again_and_replaced(store, monkeypatch, stored_run):
    """Each damage is detected before the bytes are deserialized; a whole run over a flipped
    bit computes the same and leaves a good entry."""
    _store_chunk(CONFIG.exploit)
    (path,) = store.glob("*.program")
    good, leaves = path.read_bytes(), _stored_leaves()
    assert programstore.read_entry(path, path.stem, leaves) is not None
    for what, bad in _damaged(good):
        path.write_bytes(bad)
        assert programstore.read_entry(path, path.stem, leaves) is None, what
    first, name, good = stored_run  # the run's own entry, as the run stored it
    path = store / name
    flipped = dict(_damaged(good))["a flipped bit"]
    path.write_bytes(flipped)
    _forget(monkeypatch)
    assert _run(generations=0) == first
    assert path.read_bytes() != flipped and _whole(path)  # traced again, written anew


@pytest.mark.slow
def test_a_planted_pickle_runs_nothing(store, monkeypatch, tmp_path, stored_run):
    """A pickle planted under the key (as the entry, or as the older store's ``.pkl``) is
    never unpickled: the run computes the same and the pickle's code never ran."""
    first, name, _ = stored_run
    store.mkdir(parents=True, exist_ok=True, mode=0o700)  # as the store makes it
    path = store / name  # the run's key
    marker = tmp_path / "the pickle ran"
    planted = pickle.dumps(_Plant(str(marker)))
    path.write_bytes(planted)
    path.with_suffix(".pkl").write_bytes(planted)
    _forget(monkeypatch)
    assert _run(generations=0) == first
    assert not marker.exists()
    assert _whole(path)  # replaced by a good entry


class _Plant:
    """A pickle that creates a file when it is unpickled."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.slow
def test_a_foreign_entry_is_not_used(store, monkeypatch, stored_run):
    """Another program's valid entry under this key (another engine setting) is refused by
    its manifest; with the manifest's key forged too, by its input shapes. A run over a
    foreign entry computes the same and the entry is replaced by its own."""
    _store_chunk(CONFIG.exploit)
    (path,) = store.glob("*.program")
    leaves = _stored_leaves()
    _store_chunk(CONFIG.exploit.replace(popsize=9))  # another program, its own entry
    other = _new_entry(store, {path})
    path.write_bytes(other.read_bytes())
    assert programstore.read_entry(path, path.stem, leaves) is None
    manifest, payload = _entry(other)
    path.write_bytes(json.dumps(dict(manifest, key=path.stem)).encode() + b"\n" + payload)
    assert programstore.read_entry(path, path.stem, leaves) is None
    first, name, _ = stored_run
    mine = store / name  # the run's key
    assert mine not in (path, other)
    mine.write_bytes(other.read_bytes())
    _forget(monkeypatch)
    assert _run(generations=0) == first
    assert mine.read_bytes() != other.read_bytes() and _whole(mine)


@pytest.mark.slow
@pytest.mark.parametrize("how", ["world-writable", "group-writable", "another user's"])
def test_a_folder_others_can_write_is_refused_with_one_warning(store, monkeypatch, how):
    """A store folder another user owns or may write is refused (as ssh refuses such an
    authorized_keys), with ONE warning however often it is asked: no program is read or
    written there, and the engine runs jit's own program. The compilation cache's folder
    is refused the same way (`eant2_jax.enable_compilation_cache` then turns nothing on)."""
    cache = store.parent / "xla"
    for folder in (store, cache):
        folder.mkdir(mode=0o700)
        if how != "another user's":
            folder.chmod(0o777 if how == "world-writable" else 0o770)
    if how == "another user's":
        uid = os.getuid()
        monkeypatch.setattr(os, "getuid", lambda: uid + 1)
    with pytest.warns(programstore.UntrustedFolderWarning) as caught:
        task, args = chunk_args("xor", CONFIG.exploit)
        for _ in range(2):
            stored = programstore.lookup(exploitation.run_chunk, args, {"length": 5}, task=task)
            assert stored is None
    assert len(caught) == 1 and str(store.parent) in str(caught[0].message)  # or its cache
    assert not list(store.iterdir())
    old = jax.config.jax_compilation_cache_dir
    try:
        with pytest.warns(programstore.UntrustedFolderWarning) as caught:
            assert eant2_jax.enable_compilation_cache(cache) is None
        assert len(caught) == 1 and str(cache) in str(caught[0].message)
        assert jax.config.jax_compilation_cache_dir == old
    finally:
        jax.config.update("jax_compilation_cache_dir", old)


@pytest.mark.slow
def test_a_file_not_owned_alone_is_not_read(store):
    """An entry another user could have written (group- or world-writable) is not read."""
    _store_chunk(CONFIG.exploit)
    (path,) = store.glob("*.program")
    leaves = _stored_leaves()
    assert programstore.read_entry(path, path.stem, leaves) is not None
    path.chmod(0o666)
    assert programstore.read_entry(path, path.stem, leaves) is None


@pytest.mark.slow
def test_an_unwritable_store_still_runs(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the folder would be")
    monkeypatch.setattr(programstore, "directory", lambda: blocker / "programs")
    monkeypatch.setattr(programstore, "_PROGRAMS", {})
    assert _run(generations=0)[0]
    assert blocker.read_text() == "a file where the folder would be"


def test_when_the_store_holds_nothing(store, monkeypatch):
    # A task defined outside the package: its code is not in the key.
    task = tasks.make("xor")

    class Outside(type(task)):
        pass

    Outside.__module__ = "user_tasks"
    outside = Outside(**{f: getattr(task, f) for f in task.__dataclass_fields__})
    assert programstore.lookup(exploitation.run_chunk, (outside,), {}, task=outside) is None
    # Off with the compilation cache, or alone by EANT2_PROGRAM_STORE=0.
    monkeypatch.undo()
    old = jax.config.jax_compilation_cache_dir
    try:
        jax.config.update("jax_compilation_cache_dir", None)
        assert programstore.directory() is None
        jax.config.update("jax_compilation_cache_dir", "/somewhere")
        assert programstore.directory() is not None
        monkeypatch.setenv("EANT2_PROGRAM_STORE", "0")
        assert programstore.directory() is None
    finally:
        jax.config.update("jax_compilation_cache_dir", old)


def test_the_store_follows_the_compilation_cache(tmp_path, monkeypatch):
    monkeypatch.delenv("EANT2_PROGRAM_STORE", raising=False)
    old = jax.config.jax_compilation_cache_dir
    try:
        eant2_jax.enable_compilation_cache(tmp_path / "xla")
        assert programstore.directory() == tmp_path / "xla" / programstore.DIRNAME
    finally:
        jax.config.update("jax_compilation_cache_dir", old)
    assert "eant2_jax.programs.store" in sys.modules


@pytest.mark.slow
def test_the_store_holds_a_gpu_engine_program_with_its_triton_kernel(monkeypatch):
    """A GPU engine program holds the network step's Triton kernel, a custom call that
    jax.export refuses by default (its form is not promised across versions). The store
    exports with `programstore.UNSTABLE_CUSTOM_CALLS` (its key has the JAX and jaxlib
    versions): the engine iteration, lowered for CUDA on any machine, exports with them and
    not without them. Without them a GPU process traced every engine program anew."""
    from eant2_jax import tuning
    from eant2_jax.kernels import network as kn

    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(kn, "FUSED_NEURONS", (1, kn.UNROLL_MAX))  # XOR's networks are small
    task, config = tasks.make("xor"), ExploitConfig(pruner="covariance")
    genomes = [eant2_jax.Genome.parse("N0/3*0.5 I0*1.0 I1*-1.0 B*0.1")] * 2
    keys = jax.random.split(jax.random.key(0), 2)
    prep = tuning.prepare(genomes, task, key=jax.random.key(1), config=config, keys=keys)

    def step(state):
        return exploitation.step(
            state, prep.batch.layout, prep.tables, task, jax.random.key(2), config
        )[0].cma.mean

    def exported(**checks):
        return programstore.export.export(jax.jit(step), platforms=["cuda"], **checks)(prep.state)

    text = exported(disabled_checks=programstore.UNSTABLE_CUSTOM_CALLS).mlir_module()
    assert text.count("xla.gpu.triton") == 1
    with pytest.raises(ValueError, match="xla.gpu.triton"):
        exported()
