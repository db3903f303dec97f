"""The data-only file format: plain data round-trips exactly; cut, changed, foreign and pickled files are refused."""

from __future__ import annotations

import hashlib
import json
import pickle
import random
import re
import struct
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from harness import datafile
from harness.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from harness.datafile import DataFileError, LegacyFormatError, NotPlainDataError
from harness.testing import data_difference


def _rich_tree() -> dict:
    return {
        "none": None, "bools": [True, False], "ints": [0, -3, 2**127 + 5], "text": "ünïcode $ not a tag",
        "floats": [0.1, -0.0, 1e-310, float("nan"), float("inf"), float("-inf"), 1.7976931348623157e308],
        "tuple": (1, (2.5, "x"), []), "empty": {}, "int keys": {1: "a", (2, 3): "b", None: "c"}, "$tag-like": {"$tuple": 1},
        "ordered": OrderedDict([("z", 1), ("a", 2)]),
        "arrays": [np.arange(6, dtype=np.float64).reshape(2, 3), np.zeros((0, 4), np.float32), np.array(7, np.int64),
                   np.array([True, False]), np.arange(5, dtype=">i4"), np.asfortranarray(np.ones((3, 2)))[:, ::-1],
                   np.array([1 + 2j], np.complex128), np.array([np.nan, -0.0])],
        "scalars": [np.float64(0.1), np.float32(1.5), np.int32(-4), np.bool_(True), np.uint8(255)],
        "tensors": [torch.randn(3, 4, dtype=torch.float64), torch.arange(4, dtype=torch.uint8), torch.tensor(True),
                    torch.randn(2, 2, requires_grad=True), torch.randn(4, 4).T],
        "rng": {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state(),
                "pcg": np.random.default_rng(3).bit_generator.state},
    }


def test_plain_data_round_trips_exactly(tmp_path):
    tree = _rich_tree()
    path = datafile.write(tmp_path / "f.ckpt", "checkpoint", tree, {"learner": "x"})
    meta, back = datafile.read(path, "checkpoint")
    assert meta == {"learner": "x"}
    expected = {**tree, "arrays": [a.astype(a.dtype.newbyteorder("=")) for a in tree["arrays"]],
                "tensors": [t.detach() for t in tree["tensors"]]}
    assert data_difference(expected, back) is None
    assert back["tuple"] == (1, (2.5, "x"), []) and back["int keys"][(2, 3)] == "b" and back["$tag-like"] == {"$tuple": 1}
    assert all(a.flags.writeable for a in back["arrays"]) and not back["tensors"][3].requires_grad
    # the restored states drive their generators as the saved ones
    random.setstate(back["rng"]["python"])
    np.random.set_state(back["rng"]["numpy"])
    torch.set_rng_state(back["rng"]["torch"])
    after = (random.random(), np.random.random(), torch.rand(1).item())
    random.setstate(tree["rng"]["python"])
    np.random.set_state(tree["rng"]["numpy"])
    torch.set_rng_state(tree["rng"]["torch"])
    assert after == (random.random(), np.random.random(), torch.rand(1).item())


def test_data_difference_sees_every_kind_of_change():
    a = {"x": np.array([1.0, 2.0]), "t": torch.zeros(2), "f": 0.0, "l": (1, 2)}
    assert data_difference(a, dict(a)) is None
    for changed, where in (({**a, "x": np.array([1.0, 2.0], np.float32)}, "['x']"), ({**a, "t": torch.zeros(3)}, "['t']"),
                           ({**a, "f": -0.0}, "['f']"), ({**a, "l": [1, 2]}, "['l']"), ({"x": a["x"]}, "keys")):
        assert where in data_difference(a, changed)


@dataclass
class _Thing:
    value: float


@pytest.mark.parametrize("value, where", [(_Thing(1.0), "checkpoint.learner.hyper"), (lambda x: x, "checkpoint.learner.hyper"),
                                          ({"ok": [1, object()]}, "checkpoint.learner.hyper.ok[1]"),
                                          (np.array(["a"], dtype=object), "checkpoint.learner.hyper"),
                                          (torch.zeros(2, dtype=torch.bfloat16), "checkpoint.learner.hyper")])
def test_what_is_not_plain_data_is_refused_naming_where_it_is(tmp_path, value, where):
    with pytest.raises(NotPlainDataError, match=f"^{re.escape(where)}"):
        datafile.write(tmp_path / "f.ckpt", "checkpoint", {"learner": {"hyper": value}})
    assert not list(tmp_path.iterdir())  # nothing half-written is left


class _Payload:
    """A pickle that would create a file when loaded (what a store's writer could plant)."""

    def __init__(self, target: Path) -> None:
        self.target = target

    def __reduce__(self):
        return (Path.touch, (self.target,))


def _rewritten(blob: bytes, change) -> bytes:
    """``blob`` with its header changed by ``change(header)`` and a valid checksum (a deliberate forgery)."""
    body = blob[blob.index(b"\n", len(datafile.MAGIC)) + 1:]
    (size,) = struct.unpack("<Q", body[:8])
    header = json.loads(body[8:8 + size])
    change(header)
    head = json.dumps(header).encode()
    new_body = struct.pack("<Q", len(head)) + head + body[8 + size:]
    return datafile.MAGIC + hashlib.sha256(new_body).hexdigest().encode() + b"\n" + new_body


def _set(path: tuple, value):
    def change(header):
        node = header
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return change


@pytest.mark.parametrize("change, message", [
    (_set(("arrays", 0, "dtype"), "|O"), "array 0 has dtype '|O'"),
    (_set(("arrays", 0, "offset"), 10**9), "lies outside the file"),
    (_set(("arrays", 0, "shape"), [-1]), "has shape"),
    (_set(("tree", "x"), {"$class": "os.system"}), "unknown tag"),
    (_set(("tree", "x"), {"$array": 0, "module": "os"}), "unexpected keys"),
    (_set(("tree", "x"), {"$array": 5}), "out of range"),
    (_set(("extra",), 1), "header keys"),
])
def test_a_forged_file_with_a_valid_checksum_is_refused(tmp_path, change, message):
    blob = datafile.dumps("policy", {"x": np.ones(3)})
    with pytest.raises(DataFileError, match=f"policy p.policy is not a valid harness data file .*{message}.*refused"):
        datafile.loads(_rewritten(blob, change), "policy", "p.policy")


def test_cut_changed_foreign_and_pickled_files_are_refused_with_one_line(tmp_path):
    blob = datafile.dumps("policy", {"x": np.ones(3)}, {"learner": "random"})
    errors = {}
    for label, bad in {"cut": blob[:-5], "flipped": blob[:-1] + bytes([blob[-1] ^ 1]), "empty": b"", "text": b"hello",
                       "pickle": pickle.dumps({"x": 1}), "zip": b"PK\x03\x04rest",
                       "old checkpoint": b"HARNESS-CKPT\n" + b"0" * 64 + b"\n" + pickle.dumps(1)}.items():
        name = "p.zip" if label == "zip" else "p.policy"
        with pytest.raises(DataFileError) as caught:
            datafile.loads(bad, "policy", name)
        errors[label] = caught.value
        assert "\n" not in str(caught.value) and name in str(caught.value)
    assert all("corrupt (checksum mismatch" in str(errors[k]) for k in ("cut", "flipped"))
    assert all("not a harness policy file" in str(errors[k]) for k in ("empty", "text"))
    for label in ("pickle", "zip", "old checkpoint"):
        assert isinstance(errors[label], LegacyFormatError) and "`harness store migrate RUN_ID`" in str(errors[label])
    with pytest.raises(DataFileError, match="p.ckpt is a harness 'policy' file, not a checkpoint: refused"):
        datafile.loads(blob, "checkpoint", "p.ckpt")


def test_reading_a_planted_pickle_runs_nothing(tmp_path):
    """A pickle whose loading would create a file, stored as a checkpoint and as a policy: refused, nothing ran."""
    from plugins.random_learner import RandomLearner
    from tasks.cartpole import CartPole

    target = tmp_path / "pwned"
    planted = pickle.dumps(_Payload(target))
    pickle.loads(planted)  # the payload works: loading it creates the file
    assert target.exists()
    target.unlink()
    (tmp_path / "ckpt_trial001.ckpt").write_bytes(planted)
    (tmp_path / "policy_trial001.policy").write_bytes(planted)
    with pytest.raises(LegacyFormatError):
        load_checkpoint(tmp_path / "ckpt_trial001.ckpt")
    with pytest.raises(LegacyFormatError):
        RandomLearner.load_policy(tmp_path / "policy_trial001.policy", CartPole().spec)
    assert not target.exists()


def test_a_checkpoint_holds_exactly_a_checkpoints_entries(tmp_path):
    path = save_checkpoint(Checkpoint({"a": 1}, 1, [{"trial": 1.0}], {"steps": 3}, {"w": torch.ones(2)}, {"python": random.getstate()}),
                           tmp_path / "ckpt_trial001.ckpt")
    back = load_checkpoint(path)
    assert back.trial == 1 and back.history == [{"trial": 1.0}] and torch.equal(back.learner["w"], torch.ones(2))
    datafile.write(path, "checkpoint", {"identity": {}, "trial": 1})
    with pytest.raises(DataFileError, match=r"ckpt_trial001.ckpt holds \['identity', 'trial'\], not a checkpoint's entries"):
        load_checkpoint(path)
    datafile.write(path, "checkpoint", {"identity": {}, "trial": "1", "history": [], "interaction": {}, "learner": {}, "rng": {},
                                        "version": 2})
    with pytest.raises(DataFileError, match=r"malformed entries \(trial\)"):
        load_checkpoint(path)


def test_trial_files_prefer_the_data_format_and_order_by_trial():
    names = ["policies/policy_trial010.pkl", "policies/policy_trial002.policy", "policies/policy_trial010.policy",
             "policies/policy_trial009.zip", "policies/other.txt", "policies/policy_trial003.pkl"]
    assert datafile.trial_files(names, "policy_trial") == {
        2: "policies/policy_trial002.policy", 3: "policies/policy_trial003.pkl", 9: "policies/policy_trial009.zip",
        10: "policies/policy_trial010.policy"}
    assert datafile.trial_files(reversed(names), "policy_trial")[10] == "policies/policy_trial010.policy"
