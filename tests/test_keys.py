"""``torchrl_wbrm/keys.py`` names every key that more than one file of the package uses, and the package uses those names.

The package's ``.py`` files are read with ``ast``; a string literal is a *key* where it stands in a key position:

* a subscript's index (``td["x"]``, ``td["next", "x"]``, ``record["x"] = ...``);
* the first argument of ``get``, ``set``, ``pop``, ``setdefault``, ``set_non_tensor``, ``get_non_tensor``,
  ``rename_key_``, and every argument of ``select`` and ``exclude``;
* the value of an ``in_keys``, ``out_keys``, ``in_key``, ``out_key`` or ``weight_key`` keyword argument;
* a key of a dict literal.

Two rules:

1. A key equal to one of ``keys.py``'s values is written by its name, never as a literal, outside ``keys.py``.
   ``"behaviour"`` and ``"expert"`` are also the names of a dataset's role and of configuration choices, so for them
   rule 1 covers only the positions that are TensorDict's alone (a tuple index, the methods above but ``get``/
   ``pop``/``setdefault``, the keywords).
2. A key written as a literal in TensorDict's own positions (a tuple index, ``set``, ``select``, ``exclude``,
   ``set_non_tensor``, ``get_non_tensor``, ``rename_key_``, the keywords) in two or more files is one of
   ``keys.py``'s values or one of torchrl's own names (:data:`TORCHRL_NAMES`).
"""
from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

import torchrl_wbrm.keys as keys

PACKAGE = Path(keys.__file__).resolve().parent
#: torchrl's own entry names, which the project keeps (keys.py's docstring): its env, collector and module outputs
TORCHRL_NAMES = {"observation", "action", "next", "reward", "done", "terminated", "truncated", "step_count", "loc",
                 "scale", "collector", "mask", "state_action_value", "action_value", "sample_log_prob"}
#: keys.py's values that are also ordinary words of the package (a dataset's role, a configuration choice)
SHARED_WORDS = {keys.BEHAVIOUR, keys.EXPERT}
_FIRST_ARG = {"get", "set", "pop", "setdefault", "set_non_tensor", "get_non_tensor", "rename_key_"}
_EVERY_ARG = {"select", "exclude"}
_KEYWORDS = {"in_keys", "out_keys", "in_key", "out_key", "weight_key"}
#: the positions that only a TensorDict (not a plain dict) has
_TENSORDICT_ONLY = {"tuple index", "set", "select", "exclude", "set_non_tensor", "get_non_tensor", "rename_key_",
                    "keyword"}


def _strings(node):
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        yield node
    elif isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        for element in node.elts:
            yield from _strings(element)


def key_literals(source: str) -> list[tuple[str, str, int]]:
    """``(literal, position, line)`` of every string literal in a key position of ``source`` (see the module's
    docstring); the position is ``"index"``, ``"tuple index"``, the method's name, ``"keyword"`` or ``"dict key"``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Subscript):
            where = "tuple index" if isinstance(node.slice, ast.Tuple) else "index"
            found += [(s.value, where, s.lineno) for s in _strings(node.slice)]
        elif isinstance(node, ast.Call):
            if isinstance(node.func, ast.Attribute) and node.func.attr in _FIRST_ARG | _EVERY_ARG:
                args = node.args if node.func.attr in _EVERY_ARG else node.args[:1]
                found += [(s.value, node.func.attr, s.lineno) for a in args for s in _strings(a)]
            found += [(s.value, "keyword", s.lineno) for kw in node.keywords if kw.arg in _KEYWORDS
                      for s in _strings(kw.value)]
        elif isinstance(node, ast.Dict):
            found += [(s.value, "dict key", s.lineno) for k in node.keys if k is not None for s in _strings(k)]
    return found


def named_key_violations(source: str, where: str) -> list[str]:
    """Rule 1 on one file's ``source``: every literal key equal to a value of ``keys.py``."""
    values = {getattr(keys, name): name for name in keys.__all__}
    return [f"{where}:{line}: {value!r} in a {position}: write keys.{values[value]}"
            for value, position, line in key_literals(source)
            if value in values and (value not in SHARED_WORDS or position in _TENSORDICT_ONLY)]


def unnamed_shared_keys(sources: dict[str, str]) -> dict[str, list[str]]:
    """Rule 2 over ``{file: source}``: each literal key in TensorDict's own positions that two or more files write,
    neither a value of ``keys.py`` nor torchrl's, with the files."""
    values = {getattr(keys, name) for name in keys.__all__}
    files = defaultdict(set)
    for where, source in sources.items():
        for value, position, _ in key_literals(source):
            if position in _TENSORDICT_ONLY and value not in values and value not in TORCHRL_NAMES:
                files[value].add(where)
    return {value: sorted(where) for value, where in files.items() if len(where) > 1}


def _package_sources() -> dict[str, str]:
    return {str(p.relative_to(PACKAGE.parent)): p.read_text(encoding="utf-8") for p in sorted(PACKAGE.rglob("*.py"))
            if p.name != "keys.py"}


def test_the_package_writes_keys_py_names_not_their_values():
    found = [v for where, source in _package_sources().items() for v in named_key_violations(source, where)]
    assert not found, "\n".join(found)


def test_every_key_two_files_write_is_named_in_keys_py():
    shared = unnamed_shared_keys(_package_sources())
    assert not shared, "name these in torchrl_wbrm/keys.py: " + "; ".join(f"{k!r} in {v}" for k, v in shared.items())


@pytest.mark.parametrize("line, flagged", [
    ('td.get("density_ratio")', True),
    ('td["next", "density_ratio"]', True),
    ('record["results.json"] = 1', True),
    ('{"weight_ess": ess}', True),
    ('td.select("observation", "episode")', True),
    ('TensorDictModule(net, in_keys=["observation"], out_keys=["density_ratio"])', True),
    ('td.exclude("expert")', True),                 # a shared word, in a TensorDict-only position
    ('td["behaviour", "observation"]', True),
    ('ids["expert"]', False),                       # a shared word as a plain dict's key: a dataset's role
    ('x = "density_ratio" in message', False),      # not a key position
    ('td.get(DENSITY_RATIO)', False),
])
def test_rule_one_flags_a_literal_key_of_keys_py(line, flagged):
    assert bool(named_key_violations(line, "x.py")) is flagged


def test_rule_two_flags_a_new_key_written_in_two_files():
    one, two = 'td.set("my_score", s)', 'batch.select("observation", "my_score")'
    assert unnamed_shared_keys({"a.py": one, "b.py": two}) == {"my_score": ["a.py", "b.py"]}
    assert unnamed_shared_keys({"a.py": one, "b.py": 'td.set("observation", x)'}) == {}
    assert unnamed_shared_keys({"a.py": one, "b.py": 'd.get("my_score")'}) == {}  # a plain dict may read it
