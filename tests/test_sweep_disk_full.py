"""A disk that fills up during `generate`: one line naming the store and the cases kept, exit code 1,
and the same command resumes once there is space (the failure injected, not a real full disk)."""
from __future__ import annotations

import errno

import pytest
from typer.testing import CliRunner

from cli import app
from storage.reader import PairReader
from storage.writer import PairStore

# two pressure chains of three cases, the shard written once for each
ARGS = ["generate", "--shapes", "1", "--pressures", "8,10,12", "--stiffness", "150,200", "--endo", "60", "--epi=-60",
        "--fidelity", "fast", "--nodes", "200", "--num-cpus", "1"]


@pytest.mark.slow
def test_disk_full_is_one_line_and_the_rerun_resumes(tmp_path, monkeypatch, local_ray):
    store = str(tmp_path / "s.zarr")
    real_write = PairStore.write_pairs
    calls = []

    def fills_up(self, *args, **kwargs):
        calls.append(1)
        if len(calls) > 1:  # the second chain finds the disk full
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(self, *args, **kwargs)

    monkeypatch.setattr(PairStore, "write_pairs", fills_up)
    r = CliRunner().invoke(app, ARGS + ["--store", store])
    assert r.exit_code == 1, r.output
    errors = [ln for ln in r.output.splitlines() if ln.startswith("heartctl: error:")]
    assert errors == [f"heartctl: error: disk full writing {store}; the 3 cases written are intact, free space and "
                      f"rerun the same command to resume"], r.output
    assert "Traceback" not in r.output
    assert len(PairReader(store).done_cases()) == 3
    monkeypatch.setattr(PairStore, "write_pairs", real_write)
    again = CliRunner().invoke(app, ARGS + ["--store", store])
    assert again.exit_code == 0, again.output
    assert "6 done, 0 failed of 6 (3 done and 0 failed in this run" in again.output
    reader = PairReader(store)
    assert len(reader.done_cases()) == 6 and not reader.damaged()


def test_a_quota_reached_is_a_full_disk_too(tmp_path, monkeypatch, local_ray):
    """EDQUOT, raised from inside another exception (as a library may wrap it), counts as full."""
    store = str(tmp_path / "q.zarr")

    def quota(self, *args, **kwargs):
        try:
            raise OSError(errno.EDQUOT, "Disk quota exceeded")
        except OSError as exc:
            raise RuntimeError("could not write chunk") from exc

    monkeypatch.setattr(PairStore, "write_shape", quota)
    r = CliRunner().invoke(app, ARGS + ["--store", store])
    assert r.exit_code == 1, r.output
    assert f"heartctl: error: disk full writing {store}; the 0 cases written are intact" in r.output
