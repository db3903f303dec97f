"""pilco-harness: a plugin-based benchmarking harness for data-efficient reinforcement learning.

Data flow: task (``harness.task``) -> interaction (``harness.interaction``) -> learner
(``harness.learner``, plugins) -> evaluation (``harness.evaluation``) -> run loop
(``harness.runner``) -> tracking (``harness.tracking``) -> reports.
"""

__version__ = "0.1.0"
