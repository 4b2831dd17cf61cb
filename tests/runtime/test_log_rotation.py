"""Flight-log rotation: oldest first, by count and by size, and only the runtime's own files."""

from runtime.log.rotation import LOG_GLOB, new_log_path, rotate_logs


def _logs(tmp_path, sizes: list[int]) -> list:
    paths = []
    for k, size in enumerate(sizes):
        path = new_log_path(tmp_path, k + 1, t_unix_s=1_800_000_000 + 60 * k)
        path.write_bytes(b"x" * size)
        paths.append(path)
    return paths


def test_names_sort_in_time_order(tmp_path):
    early, late = new_log_path(tmp_path, 2, t_unix_s=1_800_000_000), new_log_path(tmp_path, 1, t_unix_s=1_800_003_600)
    assert early.name == "cmnav-20270115T080000Z-ep002.mcap" and early.match(LOG_GLOB)
    assert sorted([late, early]) == [early, late]


def test_keeps_room_for_the_new_log_by_count(tmp_path):
    paths = _logs(tmp_path, [10] * 5)
    (tmp_path / "notes.txt").write_text("not a log")
    (tmp_path / "other.mcap").write_bytes(b"someone else's")
    deleted = rotate_logs(tmp_path, max_logs=3, max_total_gb=1.0)
    assert deleted == paths[:3]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([paths[3].name, paths[4].name, "notes.txt", "other.mcap"])


def test_deletes_oldest_until_under_the_size_limit(tmp_path):
    paths = _logs(tmp_path, [400, 300, 200, 100])
    deleted = rotate_logs(tmp_path, max_logs=100, max_total_gb=350e-9)  # 350 bytes
    assert deleted == paths[:2] and [p.exists() for p in paths] == [False, False, True, True]
