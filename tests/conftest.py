"""Test-session settings: the user cache (``capture.actor.template_cache``) in a temporary folder, so that
tests neither read nor fill the home folder's cache."""

from __future__ import annotations

import os

import pytest


@pytest.fixture(scope="session", autouse=True)
def _private_user_cache(tmp_path_factory):
    old = os.environ.get("CAPTURE_CACHE")
    os.environ["CAPTURE_CACHE"] = str(tmp_path_factory.mktemp("user_cache"))
    yield
    if old is None:
        os.environ.pop("CAPTURE_CACHE", None)
    else:
        os.environ["CAPTURE_CACHE"] = old
