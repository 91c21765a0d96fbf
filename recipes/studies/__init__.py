"""The studies' tooling, beside the recipes and outside the wheel: the one job runner (:mod:`studies.runs`) and the
writer of the docs' results fragments (:mod:`studies.docs_fragments`). A study script imports them as ``studies``
(``python recipes/<study>.py`` puts ``recipes/`` first on ``sys.path``)."""
