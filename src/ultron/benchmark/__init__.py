"""``ultron benchmark``: the paper's Tables 1 and 2 (and its robustness study) on the digital
phantoms, resumable and in parallel.

```python
from ultron.benchmark import BenchmarkConfig, quick_config, run_benchmark

result = run_benchmark(quick_config(), "runs/bench", log=print)
print(result.markdown)  # tables next to the paper's figures, targets met / MISSED
```

Modules: ``config`` (settings, rows), ``plan`` (task graph), ``runner`` (tasks, process
pool), ``tables`` (aggregation, markdown, targets), ``paper`` (the published figures),
``pipeline`` (``run_benchmark``, ``benchmark.json``).
"""

from ultron.benchmark.config import (
    ROBUSTNESS,
    TABLE1,
    TABLE1_ROWS,
    TABLE2,
    TABLE2_ROWS,
    BenchmarkConfig,
    quick_config,
)
from ultron.benchmark.paper import PAPER, paper_figures, paper_means
from ultron.benchmark.pipeline import (
    BENCHMARK_JSON,
    TABLES_MD,
    BenchmarkResult,
    run_benchmark,
    tables_markdown,
)
from ultron.benchmark.plan import Plan, Task, plan_benchmark
from ultron.benchmark.runner import execute, run_tasks

__all__ = [
    "BENCHMARK_JSON",
    "PAPER",
    "ROBUSTNESS",
    "TABLE1",
    "TABLE1_ROWS",
    "TABLE2",
    "TABLE2_ROWS",
    "TABLES_MD",
    "BenchmarkConfig",
    "BenchmarkResult",
    "Plan",
    "Task",
    "execute",
    "paper_figures",
    "paper_means",
    "plan_benchmark",
    "quick_config",
    "run_benchmark",
    "run_tasks",
    "tables_markdown",
]
