"""Saved-policy files: round trip and bad input."""

from __future__ import annotations

import dataclasses
import io

import pytest
import torch

from fleet_torchrl.agents import load_policy_file, save_policy
from fleet_torchrl.agents.tabular import TabularLearner
from fleet_torchrl.config import compose_config

# ---------------------------------------------------------------------- training


def test_policy_files_round_trip_and_reject_bad_input(tmp_path):
    from fleet_torchrl.agents.dqn import DQNPolicy

    cfg = compose_config(["agent=dqn"])
    pol = DQNPolicy(cfg.network, 3, "partial")
    save_policy(tmp_path / "p" / "policy.pt", pol, "dqn")
    back = load_policy_file(tmp_path / "p")
    obs = torch.rand(50, 3)
    assert torch.equal(back(obs), pol(obs)) and back.encoding == "partial"
    tab = TabularLearner().table
    tab.q.uniform_(-1, 1)
    save_policy(tmp_path / "t.pt", tab, "tabular")
    assert torch.equal(load_policy_file(tmp_path / "t.pt").q, tab.q)
    with pytest.raises(FileNotFoundError, match="no saved policy"):
        load_policy_file(tmp_path / "nothing")
    (tmp_path / "bad.pt").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="not a readable policy file"):
        load_policy_file(tmp_path / "bad.pt")
    # a text file passed by mistake: one short line, not torch's page on weights_only
    (tmp_path / "notes.md").write_text("# notes\n\nsome text\n")
    with pytest.raises(ValueError, match="notes.md is not a readable policy file") as err:
        load_policy_file(tmp_path / "notes.md")
    assert "\n" not in str(err.value) and len(str(err.value)) < 300
    assert "weights_only" not in str(err.value)
    # a file cut short (a copy interrupted): said so
    whole = (tmp_path / "p" / "policy.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(ValueError, match="cut.pt is not a readable policy file .truncated"):
        load_policy_file(tmp_path / "cut.pt")
    torch.save({"hello": 1}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="not a fleet_torchrl policy file"):
        load_policy_file(tmp_path / "foreign.pt")


def test_policy_files_written_before_the_spec_rename_still_load(tmp_path, caplog):
    """``Policy.spec()`` became ``policy_spec()`` (it shadowed TorchRL's ``spec`` attribute);
    the file keeps its ``spec`` key, so a file written before the rename, built here by hand
    as the old code wrote it, loads (with a one-line warning: it records no hash of its
    weights), and new files keep that layout plus the hashes."""
    from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig
    from fleet_torchrl.agents.policy_files import FORMAT, policy_bytes

    net = NetworkConfig(width=8, depth=1)
    pol = DQNPolicy(net, 3, "partial", anchor="heuristic", anchor_margin=2.0)
    old = {"format": FORMAT, "kind": "dqn", "encoding": "partial",
           "spec": {"network": dataclasses.asdict(net), "n_obs": 3, "encoding": "partial",
                    "anchor": "heuristic", "anchor_margin": 2.0,
                    "anchor_params": {"threshold": pol.base.threshold, "upper": pol.base.upper,
                                      "others_below": pol.base.others_below}},
           "state_dict": {k: v.detach() for k, v in pol.state_dict().items()}, "meta": {}}
    torch.save(old, tmp_path / "old.pt")
    with caplog.at_level("WARNING"):
        back = load_policy_file(tmp_path / "old.pt")
    warned = [r.getMessage() for r in caplog.records if "records no hash" in r.getMessage()]
    assert len(warned) == 1 and "\n" not in warned[0] and "old.pt" in warned[0]
    assert isinstance(back, DQNPolicy) and back.anchor == "heuristic"
    assert back.anchor_margin == 2.0 and back.network == net
    obs = torch.rand(200, 3)
    assert torch.equal(back(obs), pol(obs))
    new = torch.load(io.BytesIO(policy_bytes(pol, "dqn")), weights_only=True)
    assert new.keys() == old.keys() | {"tensors_sha256", "content_sha256"}
    assert new["spec"] == old["spec"]


# ---------------------------------------------------------------------- integrity


def _saved_bundle(tmp_path, name, policy, kind, meta=None):
    from fleet_torchrl.agents.policy_files import save_policy as save

    path = save(tmp_path / name / "policy.pt", policy, kind, meta)[0]
    return path, torch.load(path, weights_only=True)


def _write(path, bundle):
    buf = io.BytesIO()
    torch.save(bundle, buf)
    path.write_bytes(buf.getvalue())
    return path


def _all_kinds():
    from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig
    from fleet_torchrl.agents.imitation import ImitationPolicy
    from fleet_torchrl.agents.search import SearchPolicy
    from fleet_torchrl.agents.tabular import TabularQPolicy

    net = NetworkConfig(width=8, depth=1)
    mlp = SearchPolicy("mlp", hidden=4, depth=1)
    thr = SearchPolicy("threshold")
    thr.theta.copy_(torch.tensor([0.4, 0.6, 0.0, 1.0, 0.2, 0.5]))
    return {"tabular": (TabularQPolicy(), "tabular"), "dqn": (DQNPolicy(net, 3, "partial"), "dqn"),
            "anchored": (DQNPolicy(net, 6, "partial_site", "heuristic", 1.5), "dqn"),
            "table": (SearchPolicy("table", n_tc=4), "search"), "mlp": (mlp, "search"),
            "threshold": (thr, "search"),
            "student": (ImitationPolicy(16, "all", 8, 2, defer_margin=0.0), "imitation"),
            "deferring": (ImitationPolicy(3, "partial", 8, 1, defer_margin=0.5), "imitation")}


def test_every_kind_saves_with_a_hash_of_its_whole_content_and_loads_back(tmp_path):
    from fleet_torchrl.agents.policy_files import CONTENT_KEY, HASH_KEY, content_sha256

    obs = torch.rand(64, 16)
    for name, (pol, kind) in _all_kinds().items():
        path, bundle = _saved_bundle(tmp_path, name, pol, kind, meta={"seed": 1})
        assert bundle[CONTENT_KEY] == content_sha256(bundle) and HASH_KEY in bundle
        back = load_policy_file(path)
        assert type(back) is type(pol) and back.policy_spec() == pol.policy_spec(), name
        x = obs[:, :getattr(pol, "n_obs", 3)]
        assert torch.equal(back(x), pol(x)), name


def test_the_content_hash_tells_apart_what_a_decision_depends_on():
    """Values that read alike but build another policy hash apart: 1, 1.0 and True; a
    field moved between the spec and the metadata; the order of a dict's keys does not
    count (it changes no decision)."""
    from fleet_torchrl.agents.policy_files import content_sha256

    base = {"format": "f", "kind": "dqn", "encoding": "partial", "spec": {"a": 1, "b": 2},
            "meta": {}, "state_dict": {"w": torch.zeros(2)}}
    h = content_sha256(base)
    for change in ({"spec": {"a": 1.0, "b": 2}}, {"spec": {"a": True, "b": 2}},
                   {"spec": {"b": 2}, "meta": {"a": 1}}, {"spec": {"a": [1], "b": 2}},
                   {"spec": {"a": (1,), "b": 2}}, {"kind": "dqn "},
                   {"state_dict": {"w": torch.zeros(2, dtype=torch.float64)}}):
        assert content_sha256({**base, **change}) != h, change
    assert content_sha256({**base, "spec": {"b": 2, "a": 1}}) == h


def test_a_file_with_the_hash_of_its_tensors_only_loads_with_a_warning_and_upgrades(
        tmp_path, caplog):
    """A policy file written before the hash covered its spec (``tensors_sha256`` only)
    loads with one warning line (its spec is still checked as every spec is);
    ``upgrade_policy_file`` rewrites it with both hashes and its metadata, after which it
    loads without a warning and an edit of its spec is refused."""
    from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig
    from fleet_torchrl.agents.policy_files import CONTENT_KEY
    from fleet_torchrl.agents.registry import upgrade_policy_file

    pol = DQNPolicy(NetworkConfig(width=8, depth=1), 3, "partial")
    path, bundle = _saved_bundle(tmp_path, "old", pol, "dqn", meta={"seed": 7})
    del bundle[CONTENT_KEY]
    _write(path, bundle)
    with caplog.at_level("WARNING"):
        back = load_policy_file(path)
        load_policy_file(path)  # once per file and process
    warned = [r.getMessage() for r in caplog.records if "weights only" in r.getMessage()]
    assert len(warned) == 1 and "\n" not in warned[0] and str(path) in warned[0]
    assert "upgrade_policy_file" in warned[0]
    obs = torch.rand(50, 3)
    assert torch.equal(back(obs), pol(obs))
    # its spec is still validated: an edited encoding is refused without a hash to say so
    _write(tmp_path / "edited.pt", {**bundle, "spec": {**bundle["spec"], "encoding": "all"}})
    with pytest.raises(ValueError, match="disagrees with the file's declared encoding"):
        load_policy_file(tmp_path / "edited.pt")
    upgrade_policy_file(path)
    new = torch.load(path, weights_only=True)
    assert CONTENT_KEY in new and new["meta"] == {"seed": 7} and new["spec"] == bundle["spec"]
    caplog.clear()
    with caplog.at_level("WARNING"):
        assert torch.equal(load_policy_file(path)(obs), pol(obs))
    assert not caplog.records
    _write(tmp_path / "edited2.pt", {**new, "spec": {**new["spec"], "n_obs": 4}})
    with pytest.raises(ValueError, match="does not match its hash"):
        load_policy_file(tmp_path / "edited2.pt")


def test_a_key_a_policy_file_never_has_is_refused(tmp_path):
    """A flipped byte in the name of the content hash would otherwise pass the file off as
    an older one (whose spec the hash does not cover)."""
    from fleet_torchrl.agents.policy_files import CONTENT_KEY
    from fleet_torchrl.agents.tabular import TabularQPolicy

    _, bundle = _saved_bundle(tmp_path, "t", TabularQPolicy(), "tabular")
    renamed = {("cnntent_sha256" if k == CONTENT_KEY else k): v for k, v in bundle.items()}
    with pytest.raises(ValueError, match="its key 'cnntent_sha256' is not one a policy file"):
        load_policy_file(_write(tmp_path / "r.pt", renamed))


@pytest.mark.parametrize("kind,spec,match", [
    ("imitation", {"n_obs": 3, "encoding": "partial", "hidden": 0, "depth": 1},
     r"spec\.hidden=0 is invalid"),
    ("imitation", {"n_obs": 3, "encoding": "partial", "hidden": 8, "depth": 100},
     r"spec\.depth=100 is invalid"),
    ("imitation", {"n_obs": 3, "encoding": "partial", "hidden": 8, "depth": 1,
                   "defer_margin": float("nan")}, r"spec\.defer_margin=nan is invalid"),
    ("imitation", {"n_obs": 3, "encoding": "all", "hidden": 8, "depth": 1},
     "disagrees with the file's declared encoding"),
    ("imitation", {"n_obs": 3, "encoding": "partial", "hidden": 4096, "depth": 16},
     r"too large|do not fit"),
    ("search", {"policy_class": "bogus"}, r"spec\.policy_class='bogus' is invalid"),
    ("search", {"policy_class": "table", "n_tc": 1}, r"spec\.n_tc=1 is invalid"),
    ("search", {"policy_class": "table", "n_tc": 4}, r"charge is .*\[200\] in its weights "
                                                     r"but .*\[400\] by its spec"),
    ("tabular", {"x": 1}, r"spec\.x is not a field of this policy's spec .allowed: none"),
    ("dqn", {"network": {}, "n_obs": 3, "encoding": "partial", "anchor_margin": -1},
     r"spec\.anchor_margin=-1 is invalid"),
    ("dqn", {"network": {}, "n_obs": 3, "encoding": "partial", "anchor": "heuristic",
             "anchor_params": {"threshold": 400}}, r"spec\.anchor_params\.threshold=400"),
    ("dqn", {"n_obs": 3, "encoding": "partial"}, r"spec\.network is missing"),
])
def test_a_spec_is_checked_field_by_field_before_the_policy_is_built(kind, spec, match,
                                                                     tmp_path):
    """Each learner's spec (types, ranges, its fields) as a file with matching hashes
    could carry it: refused with one line naming the field."""
    from fleet_torchrl.agents.policy_files import CONTENT_KEY, content_sha256
    from fleet_torchrl.agents.search import SearchPolicy
    from fleet_torchrl.agents.tabular import TabularQPolicy

    kinds = _all_kinds()
    pol = {"imitation": kinds["deferring"][0], "search": SearchPolicy("table"),
           "tabular": TabularQPolicy(), "dqn": kinds["dqn"][0]}[kind]
    _, bundle = _saved_bundle(tmp_path, "p", pol, kind)
    bundle["spec"] = spec
    bundle[CONTENT_KEY] = content_sha256(bundle)
    with pytest.raises(ValueError, match=match) as e:
        load_policy_file(_write(tmp_path / "s.pt", bundle))
    assert "\n" not in str(e.value) and "s.pt" in str(e.value)


def test_a_network_reads_as_many_features_as_its_encoding_gives_on_the_site():
    from fleet_torchrl.agents.imitation import ImitationPolicy
    from fleet_torchrl.agents.registry import check_policy_fits_site, encoding_widths
    from fleet_torchrl.sim import SiteConfig

    assert encoding_widths("partial") == [3] and encoding_widths("partial_site") == [6]
    assert encoding_widths("all") == list(range(6, 64))
    pol = ImitationPolicy(16, "all", 8, 1)
    check_policy_fits_site(pol, SiteConfig(n_nodes=15), "p")
    with pytest.raises(ValueError, match="state=all has 21 features on this site "
                                         r"\(site.n_nodes=20\), the network reads 16"):
        check_policy_fits_site(pol, SiteConfig(n_nodes=20, n_vehicles=4), "p")


def test_a_policy_class_without_its_own_spec_check_takes_its_constructors_fields():
    """A new learner's policy need not write a spec check: its constructor's parameters
    are the fields a file's spec may hold (those without a default required)."""
    from torch import nn

    from fleet_torchrl.agents.base import Policy
    from fleet_torchrl.utils.checks import ConfigError

    class Floor(Policy):
        def __init__(self, width: int, scale: float = 1.0) -> None:
            super().__init__()
            self.lin = nn.Linear(3, width)

    Floor.check_policy_spec({"width": 4})
    Floor.check_policy_spec({"width": 4, "scale": 2.0})
    with pytest.raises(ConfigError, match=r"spec\.depth is not a field .*allowed: width, scale"):
        Floor.check_policy_spec({"width": 4, "depth": 2})
    with pytest.raises(ConfigError, match=r"spec\.width is missing"):
        Floor.check_policy_spec({})
    with pytest.raises(ConfigError, match="spec must be a dict"):
        Floor.check_policy_spec([4])


def test_a_recipes_folder_of_seeds_asks_for_one_seed(tmp_path, saved_policies):
    """``agent.policy=<a recipe's folder>`` that holds ``seed<s>/policy.pt`` only names no
    single policy: the error lists the seeds and names the first, rather than 'no policy'."""
    import shutil

    from fleet_torchrl.agents.policy_files import POLICY_FILE, read_policy_file

    src = tmp_path / "policies" / "dqn_partial" / POLICY_FILE  # the fixture's
    for s in (10, 2, 0):
        (tmp_path / "runs" / "dqn_partial" / f"seed{s}").mkdir(parents=True)
        shutil.copy(src, tmp_path / "runs" / "dqn_partial" / f"seed{s}" / POLICY_FILE)
    with pytest.raises(FileNotFoundError, match=r"seed0, seed2, seed10\): name one, e\.g\. .*"
                                                r"dqn_partial/seed0$"):
        read_policy_file(tmp_path / "runs" / "dqn_partial")
    path, _ = read_policy_file(tmp_path / "runs" / "dqn_partial" / "seed2")
    assert path == tmp_path / "runs" / "dqn_partial" / "seed2" / POLICY_FILE
