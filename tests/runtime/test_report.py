"""`cmnav report` on what is not a flight log, and the report's files under log rotation."""

import subprocess
import sys

from runtime.log.rotation import new_log_path, rotate_logs


def test_report_refuses_a_file_that_is_not_a_flight_log(tmp_path):
    bogus = tmp_path / "notes.mcap"
    bogus.write_text("not a log")
    proc = subprocess.run([sys.executable, "-m", "cmnav", "report", str(bogus)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "is not an MCAP file" in proc.stderr and "cmnav fly / cmnav sitl" in proc.stderr
    assert not bogus.with_suffix(".html").exists()


def test_rotation_deletes_a_log_with_its_report_and_leaves_other_files(tmp_path):
    old = new_log_path(tmp_path, 1, t_unix_s=1_000_000.0)
    new = new_log_path(tmp_path, 2, t_unix_s=2_000_000.0)
    for log in (old, new):
        for suffix in (".mcap", ".html", ".png"):
            log.with_suffix(suffix).write_bytes(b"x")
    notes = tmp_path / "notes.html"
    notes.write_text("keep")
    deleted = rotate_logs(tmp_path, max_logs=2, max_total_gb=1.0)
    assert deleted == [old]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([new.name, new.with_suffix(".html").name,
                                                                 new.with_suffix(".png").name, "notes.html"])  # fmt: skip
