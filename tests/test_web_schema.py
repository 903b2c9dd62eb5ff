"""Schemathesis against the app's own OpenAPI document, over real HTTP.

The ``schemathesis run`` command (every phase: examples, coverage, fuzzing,
stateful; every check, ``-c all``; bounded examples per operation) is pointed at
a running simulated station on 127.0.0.1 that already holds a calibrated job,
job 1, the job id the schema gives as its example, so the result, plot, frame and
render routes are exercised with a real result too.
It must report no failure: no server error, documented status codes, content
types and headers, responses that match their schemas, invalid data rejected,
valid data accepted, authentication enforced, a correct ``Allow`` header.

One allowance, stated in the configuration below: for ``positive_data_acceptance``
a 422 counts as an expected answer to schema-valid data, because the sweep rules
that span several fields (stop ≥ start, at most ``max_frames`` frames, the
camera's exposure range) cannot be written in JSON Schema; the station checks
them and answers 422 with field-level messages. The event stream is left out
(it stays open while a job runs); ``test_web_api`` tests it.

Jobs that schemathesis submits run on the simulated station while it tests; their
frames are rendered into a per-test copy of the frame cache, not the shared one.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_web_support import FINAL, KEY, ServerProcess, keyed, wait_for_state, write_config

SCHEMATHESIS_TOML = """
[checks]
positive_data_acceptance.expected-statuses = ["2xx", "401", "403", "404", "409", "422"]
"""


def test_the_api_passes_schemathesis(tmp_path: Path, pytestconfig: pytest.Config) -> None:
    seed_cache = Path(pytestconfig.cache.mkdir("lfcal-station-frames"))
    cache = tmp_path / "frames"
    shutil.copytree(seed_cache, cache)
    config = write_config(tmp_path / "station", width=1200, height=400)
    server = ServerProcess(config, cache=cache, analysis_workers=1)
    try:
        r = server.client.post("/api/v1/jobs", json={}, headers=keyed())
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        assert wait_for_state(server.client, job_id, FINAL, 120)["state"] == "succeeded"
        toml = tmp_path / "schemathesis.toml"
        assert job_id == 1  # the schema's example job id: the examples phase fetches its result
        toml.write_text(SCHEMATHESIS_TOML, encoding="utf-8")
        run = subprocess.run(
            [
                sys.executable,
                "-m",
                "schemathesis.cli",
                "--config-file",
                str(toml),
                "run",
                f"{server.url}/api/v1/openapi.json",
                "--header",
                f"X-API-Key: {KEY}",
                "--checks",
                "all",
                "--max-examples",
                "20",
                "--exclude-path-regex",
                "/events$",
                "--request-timeout",
                "30",
                "--no-color",
            ],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=240,
        )
        report = run.stdout[-6000:] + run.stderr[-2000:]
        assert run.returncode == 0, report
        # 15 station routes (with /results), POST /render, report.html, frame corners, /metrics
        assert "Tested: 19" in run.stdout, report
        assert "failures" not in run.stdout.split("SUMMARY")[-1].lower(), report
    finally:
        assert server.stop() == 0, server.log()
