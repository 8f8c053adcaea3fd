"""Every dialect x feed-mode program of the sample job parses in pygcode (an independent G-code
reader), and pygcode's machine model ends in the safe modal state: feed per minute (no G93 left
modal), the work offset selected, spindle and coolant off."""

import json
import re
import subprocess

import pytest

pygcode = pytest.importorskip("pygcode")

DIALECTS = ["iso", "linuxcnc", "fanuc", "sinumerik"]
FEED_MODES = ["per-minute", "inverse-time"]


@pytest.fixture(scope="module")
def sample_dwell(preston_bin, sample_job, tmp_path_factory):
    out = tmp_path_factory.mktemp("sample")
    r = subprocess.run(
        [str(preston_bin), "solve", "--job", str(sample_job), "--out", str(out), "--json", "--quiet"],
        check=True,
        capture_output=True,
        text=True,
    )
    # --json --quiet: exactly one JSON object on stdout, nothing on stderr.
    assert r.stderr == ""
    lines = r.stdout.strip().splitlines()
    assert len(lines) == 1
    assert json.loads(lines[0])["command"] == "solve"
    return out / "dwell.csv"


def words_of(line):
    """The pygcode block of one program line (raises on anything pygcode cannot read)."""
    return pygcode.Line(line).block


@pytest.mark.parametrize("dialect", DIALECTS)
@pytest.mark.parametrize("feed_mode", FEED_MODES)
def test_sample_programs_parse_in_pygcode(preston_bin, sample_job, sample_dwell, tmp_path, dialect, feed_mode):
    prog = tmp_path / "p.nc"
    subprocess.run(
        [str(preston_bin), "nc", "--dwell", str(sample_dwell), "--job", str(sample_job),
         "--dialect", dialect, "--feed-mode", feed_mode, "--spindle-rpm", "600", "--coolant",
         "--out", str(prog), "--quiet"],
        check=True,
    )
    text = prog.read_text()
    machine = pygcode.Machine()
    unknown = set()
    for n, line in enumerate(text.splitlines(), 1):
        block = words_of(line)
        for w in block.modal_params:
            unknown.add(str(w))
        # pygcode models a LinuxCNC machine: Sinumerik's G71 (metric) is its G21.
        if dialect == "sinumerik":
            block = words_of(re.sub(r"\bG71\b", "G21", line.split(";")[0]))
        try:
            machine.process_block(block)
        except Exception as e:  # pragma: no cover - the message names the line
            pytest.fail(f"{dialect} {feed_mode} line {n} {line!r}: {e}")
    # Only the dialect words pygcode does not model are left unread.
    allowed = {"G71"} if dialect == "sinumerik" else set()
    assert unknown <= allowed, unknown
    mode = machine.mode
    assert str(mode.feed_rate_mode).startswith("G94"), mode
    assert "G54" in str(mode.coordinate_system), mode
    assert "M05" in str(mode.spindle) and "M09" in str(mode.coolant), mode
    if feed_mode == "inverse-time":
        assert " G93" in text
    # Comments hold neither the block end nor a comment delimiter of another dialect.
    for line in text.splitlines():
        for body in re.findall(r"\(([^)]*)\)", line):
            assert ";" not in body and "%" not in body and "(" not in body, line
    if dialect == "sinumerik":
        assert text.startswith("%_N_PRESTON_MPF\n")
    if dialect == "fanuc":
        assert text.splitlines()[1] == "O1000"
