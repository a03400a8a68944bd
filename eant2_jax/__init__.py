"""eant2_jax: EANT2 neuro-evolution with covariance-based pruning, in JAX.

The pipeline, one module per stage: :mod:`~eant2_jax.genome` (the linear genome),
:mod:`~eant2_jax.compiler` (genomes -> padded dense layouts), :mod:`~eant2_jax.evaluate`
(the batched forward pass), :mod:`~eant2_jax.reference` (the plain NumPy interpreter every
fast path is tested against). Kernels other JAX code may import live in
:mod:`eant2_jax.kernels`.
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
from .reference import interpret as interpret

__version__ = "0.1.0"
from . import distributed as distributed
from . import tasks as tasks
from .exploitation import ExploitConfig as ExploitConfig
from .exploitation import OptimizeResult as OptimizeResult
from .exploitation import cost as cost
from .exploitation import optimize as optimize
from .loop import EANT2Config as EANT2Config
from .loop import Individual as Individual
from .loop import RunResult as RunResult
from .loop import resume as resume
from .loop import run as run
from .loop import run_many as run_many
