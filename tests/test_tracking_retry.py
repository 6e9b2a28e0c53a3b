"""Which MLflow failures the tracker retries: decided from exception types and HTTP status codes,
never from what a message says. Real failures from MlflowClient against a local HTTP stub and a
locked sqlite file; no Ray, no MLflow server."""

from __future__ import annotations

import http.server
import socket
import sqlite3
import threading

import pytest
import requests
from mlflow.exceptions import MlflowException, RestException
from mlflow.protos.databricks_pb2 import (
    INVALID_PARAMETER_VALUE,
    REQUEST_LIMIT_EXCEEDED,
    RESOURCE_DOES_NOT_EXIST,
    TEMPORARILY_UNAVAILABLE,
)

from uavlora_rllib.experiment.mlflow_client import retryable


class _Stub(http.server.BaseHTTPRequestHandler):
    """Answers every request with the server's current (status, body)."""

    def _reply(self) -> None:
        status, body = self.server.reply
        self.send_response(status)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    do_GET = do_POST = _reply

    def log_message(self, *args) -> None:
        pass


@pytest.fixture(scope="module")
def stub():
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Stub)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()


def _failure_from(uri: str, monkeypatch) -> Exception:
    """The exception MlflowClient raises for one request, with the Tracker's HTTP settings."""
    from mlflow.tracking import MlflowClient

    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "5")
    with pytest.raises(Exception) as info:
        MlflowClient(tracking_uri=uri).get_experiment_by_name("x")
    return info.value


@pytest.mark.parametrize(
    ("status", "body", "expected"),
    [
        (503, b"Service Unavailable", True),
        (503, b'{"error_code": "TEMPORARILY_UNAVAILABLE", "message": "busy"}', True),
        (429, b"slow down", True),
        (502, b"bad gateway", True),
        (504, b"gateway timeout", True),
        (500, b"error 503 while rendering", False),
        (400, b'{"error_code": "INVALID_PARAMETER_VALUE", "message": "metric 503 is not a number: 503"}', False),
        (404, b"no route /api/503", False),
    ],
)
def test_the_http_status_decides_not_the_message(stub, monkeypatch, status, body, expected):
    stub.reply = (status, body)
    exc = _failure_from(f"http://127.0.0.1:{stub.server_port}", monkeypatch)
    assert retryable(exc) is expected, (status, repr(exc))


def test_a_server_that_is_not_there_is_retried(monkeypatch):
    with socket.socket() as sock:  # a local port nothing listens on once closed
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    assert retryable(_failure_from(f"http://127.0.0.1:{port}", monkeypatch))


def test_mlflow_error_codes_map_to_status():
    assert retryable(MlflowException("503 everywhere: 503 503", error_code=INVALID_PARAMETER_VALUE)) is False
    assert retryable(MlflowException("run 503 not found", error_code=RESOURCE_DOES_NOT_EXIST)) is False
    assert retryable(RestException({"error_code": "INVALID_PARAMETER_VALUE", "message": "Temporarily 503"})) is False
    assert retryable(MlflowException("no detail", error_code=TEMPORARILY_UNAVAILABLE)) is True
    assert retryable(MlflowException("no detail", error_code=REQUEST_LIMIT_EXCEEDED)) is True


def test_requests_errors_by_type_and_status():
    def http_error(status: int) -> requests.HTTPError:
        response = requests.Response()
        response.status_code = status
        return requests.HTTPError(f"{status} but the text says 503", response=response)

    assert retryable(http_error(503)) and retryable(http_error(429))
    assert not retryable(http_error(500)) and not retryable(http_error(403))
    assert retryable(requests.ConnectionError("whatever")) and retryable(requests.Timeout("whatever"))
    assert not retryable(ValueError("Connection refused: 503 database is locked timed out"))


def test_the_root_cause_decides_through_wrappers():
    try:
        try:
            raise ConnectionRefusedError(111, "refused")
        except OSError as inner:
            raise MlflowException("API request failed") from inner  # wrapper: INTERNAL_ERROR (500)
    except MlflowException as exc:
        assert retryable(exc)


def test_a_locked_sqlite_database_is_retried_a_broken_one_not(tmp_path):
    path = tmp_path / "m.db"
    holder = sqlite3.connect(path, isolation_level=None)
    holder.execute("create table t (x)")
    holder.execute("begin exclusive")
    try:
        with pytest.raises(sqlite3.OperationalError) as locked:
            sqlite3.connect(path, timeout=0).execute("insert into t values (1)")
    finally:
        holder.execute("rollback")
        holder.close()
    with pytest.raises(sqlite3.OperationalError) as broken:
        sqlite3.connect(path).execute("select * from no_such_table")
    for cause, expected in ((locked.value, True), (broken.value, False)):
        try:
            raise MlflowException(str(cause), error_code=TEMPORARILY_UNAVAILABLE) from cause  # as MLflow's store does
        except MlflowException as exc:
            assert retryable(exc) is expected, cause
