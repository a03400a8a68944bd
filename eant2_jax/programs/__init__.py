"""Programs in one home: compiling ahead, the program store and compilation statistics.

* `eant2_jax.programs.ahead`: a jitted function's program compiled in a background thread
  (`ahead`) and the one way to call a program (`program`: compiled ahead, else stored,
  else jit's own path; each falls back by itself);
* `eant2_jax.programs.guesses`: which programs the driver starts ahead (generation 0's,
  the likely next buckets);
* `eant2_jax.programs.store`: traced programs kept on disk between processes, as data;
* `eant2_jax.programs.stats`: the process's XLA compilation counts.
"""

from . import stats as stats
from . import store as store
from .ahead import REGISTRY as REGISTRY
from .ahead import Program as Program
from .ahead import Registry as Registry
from .ahead import ahead as ahead
from .ahead import ahead_enabled as ahead_enabled
from .ahead import first_run as first_run
from .ahead import has_run as has_run
from .ahead import join_at_exit as join_at_exit
from .ahead import program as program
from .ahead import started as started
from .stats import CompileStats as CompileStats
