"""``torchrl_wbrm._files.atomic_write``, the package's one writer of whole files, and the writers that use it."""
from __future__ import annotations

import json
import os

import pytest
import torch
from tensordict import TensorDict

from torchrl_wbrm._files import atomic_write
from torchrl_wbrm.data import OfflineDatasets


def test_an_interrupted_write_keeps_the_earlier_file_and_leaves_no_temporary_file(tmp_path):
    """Any exception inside the write (here Ctrl-C) removes the temporary file and is raised as it is."""
    path = tmp_path / "log.json"
    path.write_text("earlier")

    def interrupted(f):
        f.write(b"partial")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(path, interrupted)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.json"] and path.read_text() == "earlier"


def test_saving_a_dataset_writes_its_metadata_through_the_one_writer(tmp_path, monkeypatch):
    """``OfflineDatasets.save`` writes ``metadata.json`` with ``atomic_write``: a link planted under its temporary
    name is replaced, not written through."""
    import torchrl_wbrm.data.datasets as datasets

    n = 8
    flag = torch.zeros(n, 1, dtype=torch.bool)
    rows = TensorDict({"observation": torch.randn(n, 2), "action": torch.randn(n, 2)}, [n])
    transitions = rows.clone().update({"next": {"observation": torch.randn(n, 2), "reward": torch.randn(n, 1),
                                                "done": flag, "terminated": flag, "truncated": flag}})
    data = OfflineDatasets.from_tensordicts(transitions, rows.clone(), rows.clone())
    outside = tmp_path / "outside.txt"
    outside.write_text("not yours")
    folder = tmp_path / "set"
    folder.mkdir()
    os.symlink(outside, folder / "metadata.json.tmp")
    written = []
    monkeypatch.setattr(datasets, "atomic_write", lambda path, write: (written.append(path.name),
                                                                      atomic_write(path, write))[1])
    data.save(folder)
    assert written == ["metadata.json"] and outside.read_text() == "not yours"
    assert json.loads((folder / "metadata.json").read_text())["sizes"] == data.sizes()
    assert not (folder / "metadata.json.tmp").exists()


def test_a_temporary_file_outside_the_files_folder_is_refused(tmp_path):
    """``atomic_write``'s temporary file lies beside the file it replaces: a ``tmp`` elsewhere (``../``) is refused
    before anything is created or removed there."""
    from torchrl_wbrm._files import atomic_write

    (tmp_path / "run").mkdir()
    outside = tmp_path / "keep.txt"
    outside.write_text("keep")
    with pytest.raises(ValueError, match="must lie beside"):
        atomic_write(tmp_path / "run" / "results.json", lambda f: f.write(b"{}"), tmp=tmp_path / "run" / ".." / "keep.txt")
    assert outside.read_text() == "keep" and not (tmp_path / "run" / "results.json").exists()
