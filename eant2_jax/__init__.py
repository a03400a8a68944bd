"""eant2_jax: EANT2 neuro-evolution with covariance-based pruning, in JAX.

The pipeline, one module per stage: `genome` (the linear genome),
`compiler` (genomes -> padded dense layouts), `evaluate`
(the batched forward pass), `reference` (the plain NumPy interpreter every
fast path is tested against), `exploitation` (the batched CMA-ES engine),
`pruning` (the pruning stage), `tuning` (the host/device
handover: "tune these genomes on this task"), `exploration` (mutation and
selection), `strategy` (one EANT2 generation as init/ask/exploit/tell), `loop` (the one
driver: a run, a lock-step group of runs, a resume), `multirun` (many runs over devices),
`records` (what a run records), `checkpoint` (checking and trusting a run directory),
`rundir` (crash-safe run directories), `jsonio` (strict JSON), `progress` (a ready
progress reporter). The applications
built on the library (the ``eant2`` command line, the paper's experiments, reports) live
apart, in `eant2_jax.app`. Kernels other JAX code may import live in
`eant2_jax.kernels`.
"""

from . import kernels as kernels
from .compiler import Bucket as Bucket
from .compiler import CompiledBatch as CompiledBatch
from .compiler import bucket_for as bucket_for
from .compiler import compile_genomes as compile_genomes
from .evaluate import evaluate as evaluate
from .genome import Gene as Gene
from .genome import GeneKind as GeneKind
from .genome import Genome as Genome
from .genome import GenomeError as GenomeError
from .genomefile import GenomeFile as GenomeFile
from .kernels import activations as _activations
from .loaded import LoadedNetwork as LoadedNetwork
from .loaded import load as load
from .reference import interpret as interpret

__version__ = "0.1.0"
from . import distributed as distributed
from . import export as export
from . import strategy as strategy
from . import tasks as tasks
from .config import EANT2Config as EANT2Config
from .config import enable_compilation_cache as enable_compilation_cache
from .config import enable_x64 as enable_x64
from .exploitation import ExploitConfig as ExploitConfig
from .finetune import finetune as finetune
from .loop import resume as resume
from .loop import run as run
from .loop import run_lockstep as run_lockstep
from .multirun import run_many as run_many
from .progress import ProgressReporter as ProgressReporter
from .pruning import PruneAttempt as PruneAttempt
from .records import GenerationRecord as GenerationRecord
from .records import Individual as Individual
from .records import RunResult as RunResult
from .tuning import OptimizeResult as OptimizeResult
from .tuning import cost as cost
from .tuning import optimize as optimize
from .tuning import tune as tune

register_activation = _activations.register
