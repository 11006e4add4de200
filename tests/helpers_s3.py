"""A real S3 protocol endpoint on 127.0.0.1 for the tests: moto's standalone server, as s3fs's own tests use.

A real bucket or MinIO works the same way: the code reads the endpoint from AWS_ENDPOINT_URL like any boto client.
"""

from __future__ import annotations

import logging
import os
import uuid
from collections.abc import Iterator

import pytest

from steering_core.remote import filesystems
from steering_core.storage import mirrors

S3_ENV = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1"}


@pytest.fixture(scope="session")
def s3_endpoint() -> Iterator[str]:
    """Start moto's S3 server on a free loopback port; set the standard AWS variables to it; yield its URL."""
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.WARNING)  # one line per request otherwise
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    endpoint = f"http://{host}:{port}"
    saved = {key: os.environ.get(key) for key in (*S3_ENV, "AWS_ENDPOINT_URL")}
    os.environ.update(S3_ENV, AWS_ENDPOINT_URL=endpoint)
    try:
        yield endpoint
    finally:
        server.stop()
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@pytest.fixture
def bucket(s3_endpoint: str, tmp_path, monkeypatch) -> Iterator[str]:
    """Yield a fresh bucket's URL (`s3://<name>`); this test's mirrors live in its tmp_path."""
    name = f"test-{uuid.uuid4().hex[:12]}"
    fs = filesystems.filesystem("s3")
    fs.mkdir(name)
    monkeypatch.setenv(mirrors.MIRROR_ENV, str(tmp_path / "mirror"))
    mirrors.unmount_all()
    try:
        yield f"s3://{name}"
    finally:
        mirrors.unmount_all()
        fs.invalidate_cache()
