"""Started worker processes: a script that asks for them at module level, outside its ``__main__`` guard, gets an
error naming its line instead of a run that hangs for ever; guarded scripts, ``python -c`` and functions called
from a guard start their workers."""
import subprocess
import sys
import textwrap

import pytest

POOL = """
from concurrent.futures import ProcessPoolExecutor
from occflownet.worker_processes import spawn_context

def run_pool():
    with ProcessPoolExecutor(2, mp_context=spawn_context()) as pool:
        print("squares", sorted(pool.map(abs, [-3, 2, -1])))
"""


def _run_script(tmp_path, body: str, timeout: float = 120) -> subprocess.CompletedProcess:
    script = tmp_path / "user_script.py"
    script.write_text(textwrap.dedent(POOL) + textwrap.dedent(body))
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=timeout,
                          cwd=tmp_path)


@pytest.mark.parametrize("body", [
    'if __name__ == "__main__":\n    run_pool()\n',
    'def main():\n    run_pool()\n\nif "__main__" == __name__:\n    main()\n',
    'if __name__ == "__main__":\n    import sys\n    if len(sys.argv) < 5:\n        run_pool()\n',
])
def test_guarded_scripts_start_their_workers(tmp_path, body):
    res = _run_script(tmp_path, body)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "squares [1, 2, 3]" in res.stdout


def test_an_unguarded_call_is_refused_with_the_line_before_any_worker_starts(tmp_path):
    res = _run_script(tmp_path, "x = 1\nrun_pool()\n")
    assert res.returncode != 0
    assert "UnguardedMainError" in res.stderr and "user_script.py, line 9" in res.stderr, res.stderr[-2000:]
    assert '__name__ == "__main__"' in res.stderr and "squares" not in res.stdout


def test_a_guard_further_up_does_not_cover_a_later_unguarded_call(tmp_path):
    res = _run_script(tmp_path, 'if __name__ == "__main__":\n    pass\nrun_pool()\n')
    assert res.returncode != 0 and "UnguardedMainError" in res.stderr, res.stderr[-2000:]


def test_a_packages_main_run_with_dash_m_is_not_run_again_and_starts_its_workers(tmp_path):
    # spawn does not import a package's __main__ again (python -m occflownet is one): no guard needed there; a
    # plain module run with -m is imported again, so it needs one
    package = tmp_path / "userpkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "__main__.py").write_text(textwrap.dedent(POOL) + "run_pool()\n")
    (package / "job.py").write_text(textwrap.dedent(POOL) + "run_pool()\n")
    ran = subprocess.run([sys.executable, "-m", "userpkg"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr[-2000:]
    assert "squares [1, 2, 3]" in ran.stdout
    refused = subprocess.run([sys.executable, "-m", "userpkg.job"], capture_output=True, text=True, timeout=120,
                             cwd=tmp_path)
    assert refused.returncode != 0 and "UnguardedMainError" in refused.stderr, refused.stderr[-2000:]


def test_python_c_starts_its_workers(tmp_path):
    code = textwrap.dedent(POOL) + "run_pool()\n"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "squares [1, 2, 3]" in res.stdout


def test_train_from_an_unguarded_script_fails_with_the_line_instead_of_hanging(prepared_synth_root, tmp_path):
    # before the check, this run waited for ever in popen_spawn_posix._launch (its first worker died importing
    # the script again while the parent was still writing the worker's payload)
    root, _ = prepared_synth_root
    script = tmp_path / "train_script.py"
    script.write_text(textwrap.dedent(f"""
        from occflownet.train.loop import train
        from occflownet.train.recipe import TrainConfig
        train(TrainConfig(preset="tiny", dataroot={str(root)!r}, out={str(tmp_path / 'run')!r}, split="all",
                          max_steps=2, rays_per_step=512, num_workers=1), progress=False)
    """))
    res = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert res.returncode != 0
    assert "UnguardedMainError" in res.stderr and "train_script.py, line 4" in res.stderr, res.stderr[-2000:]
