"""benchmarks/kernel_counters.py's reading of Nsight Compute's CSV, on a hand-written sample."""

import pytest

from benchmarks.kernel_counters import measured_update, parse_details_csv, table

HEADER = (
    '"ID","Process ID","Process Name","Host Name","Kernel Name","Context","Stream",'
    '"Block Size","Grid Size","Device","CC","Section Name","Metric Name","Metric Unit","Metric Value"'
)


def _row(kid, name, section, metric, unit, value, grid="(307, 1, 1)"):
    return (
        f'"{kid}","7","python3","host","{name}","1","13","(64, 1, 1)","{grid}","0","9.0",'
        f'"{section}","{metric}","{unit}","{value}"'
    )


def _sample():
    sol = "GPU Speed Of Light Throughput"
    lines = ["==PROF== Connected to process 7", "some output of the program", HEADER]
    # a set-up kernel, then two updates of the same two kernels
    for kid, name, ns in [(0, "_conv_kernel", "9,000"), (1, "_conv_kernel", "170,424"),
                          (2, "_wgrad_kernel", "150,590"), (3, "_conv_kernel", "171,000"),
                          (4, "_wgrad_kernel", "151,200")]:  # fmt: skip
        lines.append(_row(kid, name, sol, "Duration", "nsecond", ns))
        lines.append(_row(kid, name, sol, "L2 Cache Throughput", "%", "61.25"))
        lines.append(
            _row(kid, name, "Launch Statistics", "Registers Per Thread", "register/thread", "128")
        )
        lines.append(_row(kid, name, "Launch Statistics", "Cache Config", "", "CachePreferNone"))
    lines.append("==PROF== Disconnected from process 7")
    return "\n".join(lines)


def test_parse_reads_every_kernel_and_metric_with_units():
    kernels = parse_details_csv(_sample())
    assert [k["id"] for k in kernels] == [0, 1, 2, 3, 4]
    names = [k["name"] for k in kernels]
    assert names == ["_conv_kernel"] * 2 + ["_wgrad_kernel", "_conv_kernel", "_wgrad_kernel"]
    m = kernels[1]["metrics"]
    assert m["GPU Speed Of Light Throughput / Duration"] == [170424.0, "nsecond"]  # "170,424"
    assert m["GPU Speed Of Light Throughput / L2 Cache Throughput"] == [61.25, "%"]
    assert m["Launch Statistics / Registers Per Thread"] == [128.0, "register/thread"]
    assert m["Launch Statistics / Cache Config"] == ["CachePreferNone", ""]  # text stays text
    assert kernels[1]["grid"] == "(307, 1, 1)" and kernels[1]["block"] == "(64, 1, 1)"


def test_the_measured_update_is_the_repeated_tail():
    kernels = parse_details_csv(_sample())
    last = measured_update(kernels)
    assert [k["id"] for k in last] == [3, 4]
    with pytest.raises(ValueError, match="no repeated update"):
        measured_update(kernels[:4])  # conv, conv, wgrad, conv: no tail repeats
    with pytest.raises(ValueError, match="no ncu CSV header"):
        parse_details_csv("==PROF== Error: no kernels were profiled")


def test_table_gives_durations_in_microseconds_and_dashes_for_missing_metrics():
    rows = table(measured_update(parse_details_csv(_sample()))).splitlines()
    assert rows[0].startswith("| # | kernel | grid | us | DRAM % | L2 % |")
    cells = [c.strip() for c in rows[2].strip("|").split("|")]
    assert cells[:7] == ["0", "_conv_kernel", "(307, 1, 1)", "171.0", "-", "61.2", "-"]
    assert cells[-1] == "128.0"


def test_main_runs_ncu_and_writes_the_measured_update(tmp_path, monkeypatch, capsys):
    """The whole command against a stand-in ncu that prints the sample: the target it is handed
    is this script's own, without command buffers or a preallocated pool; ncu's messages and the
    program's output pass to stderr, the CSV is kept beside the JSON, the JSON holds the last
    update."""
    import json
    import pathlib
    import sys

    from benchmarks import kernel_counters

    fake = tmp_path / "ncu"
    sample = tmp_path / "sample.csv"
    sample.write_text(_sample())
    argv_log = tmp_path / "argv.json"
    fake.write_text(
        f"#!{sys.executable}\nimport json, os, sys\n"
        "env = [os.environ[k] for k in ('XLA_FLAGS', 'XLA_PYTHON_CLIENT_PREALLOCATE',"
        "                               'JAX_COMPILATION_CACHE_DIR')]\n"
        f"json.dump([*env, *sys.argv[1:]], open({str(argv_log)!r}, 'w'))\n"
        f"print(open({str(sample)!r}).read())\n"
    )
    fake.chmod(0o755)
    out = tmp_path / "counters.json"
    monkeypatch.setattr(
        sys, "argv", ["kernel_counters.py", "--ncu", str(fake), "--seeds", "2", "--out", str(out)]
    )
    warm_ups = []
    monkeypatch.setattr(
        kernel_counters.subprocess, "check_call", lambda cmd, env: warm_ups.append((cmd, env))
    )
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    kernel_counters.main()
    xla_flags, preallocate, cache, *argv = json.loads(argv_log.read_text())
    assert "--xla_gpu_enable_command_buffer=" in xla_flags.split()  # each kernel on its own
    assert preallocate == "false"
    assert argv[:6] == [
        "--clock-control",
        "none",
        "--target-processes",
        "application-only",
        "--kernel-name",
        "regex:_conv_kernel|_wgrad_kernel",
    ]
    target = argv[argv.index(sys.executable) :]
    assert target[1:4] == ["-m", "benchmarks.kernel_counters", "--target"]
    assert target[target.index("--seeds") + 1] == "2"
    # the same target ran first outside ncu, every program into a fresh persistent cache
    [(warm_up, env)] = warm_ups
    assert warm_up == target and env["XLA_FLAGS"] == xla_flags
    assert env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == "0"
    assert env["JAX_COMPILATION_CACHE_DIR"] == cache and cache
    assert not pathlib.Path(cache).exists()  # the temporary one, removed
    result = json.loads(out.read_text())
    assert [k["id"] for k in result["kernels"]] == [3, 4]
    csv_lines = [line for line in _sample().splitlines() if line.startswith('"')]
    assert out.with_suffix(".csv").read_text().splitlines() == csv_lines
    printed = capsys.readouterr()
    assert "| 1 | _wgrad_kernel |" in printed.out
    assert printed.err.splitlines()[:3] == [
        "compiling outside ncu",
        "==PROF== Connected to process 7",
        "some output of the program",
    ]
