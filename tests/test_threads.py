"""Thread choice on a shared machine: quotas, /proc/stat sampling, the wait policy, the CLI option."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from narf_core import threads
from narf_core.cli import main


def test_cgroup_quota_in_cores(tmp_path: Path) -> None:
    f = tmp_path / "cpu.max"
    f.write_text("150000 100000\n")
    assert threads.cgroup_cpu_limit(f) == pytest.approx(1.5)
    f.write_text("max 100000\n")
    assert threads.cgroup_cpu_limit(f) is None
    f.write_text("garbage\n")
    assert threads.cgroup_cpu_limit(f) is None
    assert threads.cgroup_cpu_limit(tmp_path / "absent") is None


def test_cpu_times_sum_only_the_allowed_cpus(tmp_path: Path) -> None:
    stat = tmp_path / "stat"
    stat.write_text(textwrap.dedent("""\
        cpu  100 0 100 800 0 0 0 0 0 0
        cpu0 10 0 10 70 10 0 0 0 0 0
        cpu1 50 0 30 20 0 0 0 0 0 0
        cpu2 1000 0 0 0 0 0 0 0 0 0
        intr 12345
    """))
    busy, total = threads._cpu_times([0, 1], stat)
    assert (busy, total) == (100.0, 200.0)  # cpu2 is not ours; idle + iowait are not busy


def test_a_busy_process_is_seen_and_our_own_work_is_not() -> None:
    spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        seen = threads.busy_cores(0.5)
    finally:
        spin.kill()
        spin.wait()
    assert seen >= 0.6, seen
    assert 1 <= threads.free_cores(0.05) <= threads.available_cores()


def test_choose_threads() -> None:
    assert threads.choose_threads(3) == 3
    assert 1 <= threads.choose_threads("auto") <= threads.available_cores()
    assert threads.choose_threads("auto", share=64) == 1
    for bad in (0, -2, True, 1.5, "many"):
        with pytest.raises(ValueError, match="threads"):
            threads.choose_threads(bad)


def test_torch_threads_sets_the_count_for_the_block_and_restores_it() -> None:
    """``torch_threads(n)``: n threads inside the block, the count before it after, also after an error."""
    import torch

    before = torch.get_num_threads()
    target = 1 if before != 1 else 2
    with threads.torch_threads(target):
        assert torch.get_num_threads() == target
    assert torch.get_num_threads() == before
    with pytest.raises(KeyError), threads.torch_threads(target):
        raise KeyError("inside")
    assert torch.get_num_threads() == before


def test_parse_threads() -> None:
    assert threads.parse_threads(" AUTO ") == "auto"
    assert threads.parse_threads("2") == 2
    for bad in ("0", "-1", "two", ""):
        with pytest.raises(ValueError, match="'auto' or a positive integer"):
            threads.parse_threads(bad)


def test_passive_wait_unless_the_user_chose(monkeypatch) -> None:
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    assert threads.prefer_passive_wait() is True
    monkeypatch.setenv("OMP_WAIT_POLICY", "active")
    assert threads.prefer_passive_wait() is False
    assert threads.prefer_passive_wait.__module__ == "narf_core.threads"


@pytest.mark.parametrize("entry", ["import narf_service", "from narf_core.cli import main; main(['bench', 'render', '--quick', '--models', '/absent'])"])
def test_entry_points_set_the_policy_before_torch_loads(entry: str) -> None:
    """The policy the process had when torch was first imported (libgomp reads it then, once)."""
    code = textwrap.dedent(f"""\
        import builtins, os, sys
        real_import = builtins.__import__
        def spy(name, *args, **kwargs):
            if name == "torch" and "torch" not in sys.modules:
                print("policy:", os.environ.get("OMP_WAIT_POLICY"), flush=True)
            return real_import(name, *args, **kwargs)
        builtins.__import__ = spy
        try:
            {entry}
        except SystemExit:
            pass
        import torch
    """)
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.splitlines()[0] == "policy: PASSIVE", out.stdout


def test_cli_threads_option(capsys, monkeypatch) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--threads", "0", "bench", "render", "--quick"])
    assert exit_info.value.code == 2
    assert "--threads: threads must be 'auto' or a positive integer, got 0" in capsys.readouterr().err
    monkeypatch.setenv("NARF_THREADS", "lots")
    from narf_core.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["bench", "render", "--quick"])
    assert "got 'lots'" in capsys.readouterr().err


def test_auto_takes_one_thread_of_the_free_cores_for_every_command(monkeypatch) -> None:
    """``auto``: one thread where a core is free, training included (its parallel regions of a few thousand
    rays gain nothing from a second thread that sleeps between them); ``--threads N`` is taken as it is."""
    from narf_core.cli import _threads_for, build_parser

    monkeypatch.setattr(threads, "free_cores", lambda interval_s=0.1: 2)

    def chosen(*argv: str) -> int:
        return _threads_for(build_parser().parse_args(list(argv)))

    assert chosen("--threads", "auto", "track", "m.narf", "seq", "--init-pose", "label") == 1
    assert chosen("--threads", "auto", "bench", "estimate", "--quick") == 1
    assert chosen("--threads", "auto", "train", "data", "--out", "m.narf") == 1
    assert chosen("--threads", "2", "track", "m.narf", "seq", "--init-pose", "label") == 2
    assert chosen("--threads", "2", "train", "data", "--out", "m.narf") == 2
    monkeypatch.setattr(threads, "free_cores", lambda interval_s=0.1: 1)
    assert chosen("--threads", "auto", "train", "data", "--out", "m.narf") == 1
