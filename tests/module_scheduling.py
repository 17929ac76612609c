"""pytest-xdist scheduling by test module: a module runs whole on one worker, so that its module
fixtures (a trained model, a whole tiny demo) are built once, and named modules share one work
unit, so that a session fixture they share is built once too. Work units are handed out in
collection order (conftest puts the slow modules first)."""

from __future__ import annotations

from pathlib import PurePosixPath

from xdist.scheduler import LoadScopeScheduling


class ModuleScheduling(LoadScopeScheduling):
    """``LoadScopeScheduling`` whose scope is the test module, or the group its file name is given
    in ``groups`` (``{"test_x.py": "group"}``)."""

    def __init__(self, config, log=None, groups: dict[str, str] | None = None) -> None:
        super().__init__(config, log)
        self.groups = dict(groups or {})
        config.option.loadscopereorder = False  # keep the collection order (not: most tests first)

    def _split_scope(self, nodeid: str) -> str:
        module = nodeid.split("::", 1)[0]
        return self.groups.get(PurePosixPath(module).name, module)
