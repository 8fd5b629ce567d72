"""The benchmark of magenv ("magenv-bench v1"): its tasks (:mod:`magenv.benchmark.suite`) and how a policy is
scored on them (:mod:`magenv.benchmark.score`); ``magenv benchmark`` runs it (``magenv.train.benchmark``)."""
