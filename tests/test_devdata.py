"""The development data folder is found the same way by every bench and by the tests."""

from __future__ import annotations

from pathlib import Path

from services.common import devdata
from services.localization.slam import bench_fr079

SERVICES = Path(__file__).resolve().parents[1] / "services"


def test_benches_find_the_data_the_tests_use(shared_dir: Path) -> None:
    assert devdata.shared_dir().resolve() == shared_dir.resolve()
    assert (bench_fr079._logs_dir() / "fr079.orig.bag").is_file()


def test_one_place_reads_zagv_shared() -> None:
    readers = sorted(str(p.relative_to(SERVICES)) for p in SERVICES.rglob("*.py") if "ZAGV_SHARED\"" in p.read_text())
    assert readers == ["common/devdata.py"], readers
