"""The pytest-xdist scheduling of ``make test`` (tests/module_scheduling.py): whole modules per
worker, grouped modules together, work handed out in collection order."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

pytest.importorskip("xdist")

from module_scheduling import ModuleScheduling  # noqa: E402


class FakeWorker:
    """What the scheduler calls on a worker: records the test indices sent to it."""

    def __init__(self, name: str) -> None:
        self.gateway = SimpleNamespace(id=name)
        self.sent: list[int] = []
        self.shutting_down = False

    def send_runtest_some(self, indices) -> None:
        self.sent += list(indices)

    def shutdown(self) -> None:
        self.shutting_down = True


def _scheduled(collection: list[str], groups: dict[str, str]) -> dict[str, set[str]]:
    config = SimpleNamespace(getvalue=lambda name: ["2*popen"] if name == "tx" else None,
                             option=SimpleNamespace(loadscopereorder=True))
    scheduler = ModuleScheduling(config, None, groups)
    workers = [FakeWorker("gw0"), FakeWorker("gw1")]
    for worker in workers:
        scheduler.add_node(worker)
        scheduler.add_node_collection(worker, collection)
    scheduler.schedule()
    done: dict[str, int] = {w.gateway.id: 0 for w in workers}
    while not scheduler.tests_finished:  # each worker runs what it was sent, one test at a time
        for worker in workers:
            if done[worker.gateway.id] < len(worker.sent):
                scheduler.mark_test_complete(worker, worker.sent[done[worker.gateway.id]])
                done[worker.gateway.id] += 1
    return {w.gateway.id: {collection[i] for i in w.sent} for w in workers}


def test_a_module_runs_whole_on_one_worker_and_grouped_modules_together():
    collection = ["tests/test_slow.py::test_0"] + [f"tests/test_{name}.py::test_{i}" for name in "abcde"
                                                   for i in range(3)]
    sent = _scheduled(collection, {"test_b.py": "shared", "test_c.py": "shared"})
    modules = {worker: {nodeid.split("::")[0] for nodeid in ids} for worker, ids in sent.items()}
    assert set().union(*sent.values()) == set(collection)
    assert modules["gw0"].isdisjoint(modules["gw1"])  # no module split across workers
    assert any({"tests/test_b.py", "tests/test_c.py"} <= m for m in modules.values())
    # collection order (the slow modules first), not the default "most tests first"
    assert "tests/test_slow.py" in modules["gw0"] and "tests/test_a.py" in modules["gw1"]


def test_the_scope_is_the_module_or_its_group():
    scheduler = ModuleScheduling.__new__(ModuleScheduling)
    scheduler.groups = {"test_b.py": "shared"}
    assert scheduler._split_scope("tests/test_a.py::test_x[1-2]") == "tests/test_a.py"
    assert scheduler._split_scope("tests/test_a.py::Class::test_y") == "tests/test_a.py"
    assert scheduler._split_scope("tests/test_b.py::test_z") == "shared"
