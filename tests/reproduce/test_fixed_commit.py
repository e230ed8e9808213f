"""io.fixed_commit: within a reproduction git is asked once per source tree for every manifest's commit, and the
answer is git's (issue 20: three git processes per artefact before)."""

import subprocess
from pathlib import Path

from netkf_cli.runtime import io

ROOT = Path(__file__).resolve().parents[2]


def test_git_is_asked_once_per_tree_within_the_block_and_every_time_outside(monkeypatch):
    asked = []
    monkeypatch.setattr(io, "_ask_git", lambda cwd: asked.append(str(cwd)) or f"sha{len(asked)}")
    assert io.git_commit(ROOT) == "sha1" and io.git_commit(ROOT) == "sha2"
    with io.fixed_commit():
        assert [io.git_commit(ROOT) for _ in range(3)] == ["sha3"] * 3
        assert io.git_commit(ROOT / "netkf_cli") == "sha4"  # another directory is asked on its own
    assert io.git_commit(ROOT) == "sha5"
    assert len(asked) == 5


def test_the_fixed_answer_is_gits():
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, timeout=5)
    except OSError:
        head = None
    with io.fixed_commit():
        got = io.git_commit(ROOT)
    if head is None or head.returncode != 0:  # not a git checkout (an sdist): no commit either way
        assert got is None
    else:
        assert got is not None and got.split("+")[0] == head.stdout.strip()
        assert got == io.git_commit(ROOT)
