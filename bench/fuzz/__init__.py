"""The fuzz's targets, one module each (issue 40 item 5), run by ``python -m bench
fuzz_rundir`` (`bench.bench_fuzz_rundir`):

* `bench.fuzz.common`: the classes every case ends in, the marker file hostile payloads
  create, and the payloads themselves;
* `bench.fuzz.manifests`: reproduction manifests (``reproduce.json``);
* `bench.fuzz.headers`: genome files' headers (``eant2 show``, `eant2_jax.load`, ``to_jax``);
* `bench.fuzz.store`: program-store entries (`eant2_jax.programs.store`);
* `bench.fuzz.options`: gymnax, brax and Playground task options.

Each target module has ``run(rng, n, tmp) -> (counts by case kind, bugs)`` and uses only
the library's public names, so it keeps working while the modules it fuzzes change.
"""
