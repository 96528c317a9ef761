"""Quality-Diversity engine: containers, emitters, the MAP-Elites loop, task specs, metrics, files, plots."""

from hte_jax.qd.archive import Archive
from hte_jax.qd.batched import BatchedMapElites
from hte_jax.qd.emitters import Emitter, EmptyState, VariationEmitter
from hte_jax.qd.grid import Grid
from hte_jax.qd.io import CheckpointError, load_checkpoint, save_checkpoint
from hte_jax.qd.loop import MapElites, MapElitesConfig, QDState, resume, run
from hte_jax.qd.metrics import RepertoireMetrics, repertoire_metrics
from hte_jax.qd.repertoire import Evaluation, Insertion, Repertoire
from hte_jax.qd.selection import UniformSelection
from hte_jax.qd.store import load_repertoire, save_repertoire
from hte_jax.qd.task_spec import TaskSpec
from hte_jax.qd.variation import SbxPolynomial

__all__ = ["Archive", "BatchedMapElites", "CheckpointError", "Emitter", "EmptyState", "Evaluation", "Grid",
           "Insertion", "MapElites", "MapElitesConfig", "QDState", "Repertoire", "RepertoireMetrics", "SbxPolynomial",
           "TaskSpec", "UniformSelection", "VariationEmitter", "load_checkpoint", "load_repertoire",
           "repertoire_metrics", "resume", "run", "save_checkpoint", "save_repertoire"]
