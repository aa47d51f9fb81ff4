import pytest
from sqlalchemy.exc import OperationalError

from carp.sweep import worker


class SchemaRace:
    """Stands in for `RDBStorage`: the first `failures` opens raise `error`, as when another worker creates the
    tables at the same moment."""

    def __init__(self, error: Exception, failures: int = 1) -> None:
        self.error = error
        self.failures = failures
        self.opened = 0

    def __call__(self, *args, **kwargs) -> str:
        self.opened += 1
        if self.opened <= self.failures:
            raise self.error
        return "storage"


def _sqlite_error(message: str) -> OperationalError:
    return OperationalError("CREATE TABLE studies (...)", {}, Exception(message))


@pytest.mark.parametrize("table", ["studies", "version_info"])
def test_storage_opens_again_when_another_worker_created_the_sqlite_tables_first(sweep_config, monkeypatch, table):
    race = SchemaRace(_sqlite_error(f"table {table} already exists"))
    monkeypatch.setattr(worker, "RDBStorage", race)
    monkeypatch.setattr(worker.time, "sleep", lambda seconds: None)
    assert worker.open_storage(sweep_config) == "storage" and race.opened == 2


def test_other_operational_errors_are_not_retried(sweep_config, monkeypatch):
    race = SchemaRace(_sqlite_error("unable to open database file"))
    monkeypatch.setattr(worker, "RDBStorage", race)
    monkeypatch.setattr(worker.time, "sleep", lambda seconds: None)
    with pytest.raises(OperationalError, match="unable to open database file"):
        worker.open_storage(sweep_config)
    assert race.opened == 1


def test_a_schema_race_that_never_settles_is_reported(sweep_config, monkeypatch):
    race = SchemaRace(_sqlite_error("table studies already exists"), failures=worker.SCHEMA_ATTEMPTS)
    monkeypatch.setattr(worker, "RDBStorage", race)
    monkeypatch.setattr(worker.time, "sleep", lambda seconds: None)
    with pytest.raises(OperationalError, match="already exists"):
        worker.open_storage(sweep_config)
    assert race.opened == worker.SCHEMA_ATTEMPTS
