#!/usr/bin/env python3
"""Cross-file checks of deploy/ that schema validators cannot make (run by deploy/validate.sh).

The JSON-schema validators see one document at a time. This checks what ties the files
together:

  compose     deploy/compose.yaml: depends_on targets exist and have the healthcheck or the
              one-shot restart policy their condition needs, published ports are on loopback,
              every ${VAR} has a default, named volumes are declared, the build's Dockerfile
              exists, and every RELREWARD__* variable is a real configuration key.
  k8s         deploy/k8s: kustomization.yaml lists every manifest and nothing missing, the
              ConfigMap's config.toml only has real keys with the right types, Secret keys are
              real keys, names and label selectors meet, probes hit a declared port, the
              grace periods outlast preStop + the server's drain and grace, and the serving
              pods' drain outlasts their readiness probe's detection (period x failures).
  dockerfile  deploy/Dockerfile: its RELREWARD__* ENV keys are real configuration keys.

"Real configuration key" means present in deploy/config.example.toml, which lists every key.
Usage: checks.py compose|k8s|dockerfile ... (several at once allowed). Exit 1 on any problem.
"""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path

import yaml

DEPLOY = Path(__file__).resolve().parent
EXAMPLE = DEPLOY / "config.example.toml"
LOOPBACK = {"127.0.0.1", "::1", "[::1]", "localhost"}
ROLES = {"serve", "work", "all"}
PREFIX = "RELREWARD__"


class Problems(list):
    def add(self, where: str, message: str) -> None:
        self.append(f"{where}: {message}")


def config_schema() -> dict:
    return tomllib.loads(EXAMPLE.read_text())


def lookup(schema: dict, path: list[str]):
    """The example's value at path, or KeyError."""
    node = schema
    for part in path:
        if not isinstance(node, dict) or part not in node:
            raise KeyError(".".join(path))
        node = node[part]
    return node


def check_env_key(name: str, schema: dict, where: str, problems: Problems) -> None:
    if not name.startswith(PREFIX):
        return
    path = name[len(PREFIX) :].lower().split("__")
    try:
        lookup(schema, path)
    except KeyError:
        problems.add(where, f"{name} is not a configuration key ({'.'.join(path)} is not in {EXAMPLE.name})")


def same_type(example, value) -> bool:
    # bool is an int in Python; TOML keeps them apart.
    if isinstance(example, bool) or isinstance(value, bool):
        return isinstance(example, bool) and isinstance(value, bool)
    return isinstance(value, type(example))


def check_toml_keys(doc: dict, schema: dict, where: str, problems: Problems, prefix: str = "") -> None:
    for key, value in doc.items():
        dotted = f"{prefix}{key}"
        if key not in schema:
            problems.add(where, f"{dotted} is not a configuration key (not in {EXAMPLE.name})")
            continue
        example = schema[key]
        if isinstance(example, dict):
            if not isinstance(value, dict):
                problems.add(where, f"{dotted} must be a table")
            else:
                check_toml_keys(value, example, where, problems, dotted + ".")
        elif not same_type(example, value):
            problems.add(
                where, f"{dotted} = {value!r} has type {type(value).__name__}, expected {type(example).__name__}"
            )


# --- compose ---------------------------------------------------------------------------------

INTERPOLATION = re.compile(r"\$(\$|\{([^}]*)\}|([A-Za-z_][A-Za-z0-9_]*))")


def strings(node):
    if isinstance(node, str):
        yield node
    elif isinstance(node, dict):
        for k, v in node.items():
            yield from strings(k)
            yield from strings(v)
    elif isinstance(node, list):
        for v in node:
            yield from strings(v)


def published_host_ip(port) -> str | None:
    """The host address a port entry publishes on; None when it publishes none."""
    if isinstance(port, dict):
        if port.get("published") is None:
            return None
        return str(port.get("host_ip", ""))
    text = str(port).split("/")[0]
    if text.startswith("["):  # [::1]:50051:50051
        host, _, rest = text[1:].partition("]:")
        return host if ":" in rest else ""
    parts = text.split(":")
    if len(parts) == 1:
        return ""  # container port only: Docker publishes it on every address
    return parts[0] if len(parts) == 3 else ""


def check_compose(path: Path, problems: Problems) -> None:
    where = str(path.relative_to(DEPLOY.parent))
    doc = yaml.safe_load(path.read_text())
    schema = config_schema()
    services = doc.get("services") or {}
    volumes = set((doc.get("volumes") or {}).keys())
    if not services:
        problems.add(where, "no services")

    # YAML anchors repeat a string in every service that merges it: report each once.
    undefaulted = set()
    for text in strings(doc):
        for m in INTERPOLATION.finditer(text):
            if m.group(1) == "$":
                continue
            expr = m.group(2) if m.group(2) is not None else m.group(3)
            if m.group(3) is not None or not re.search(r":?[-?]", expr):
                undefaulted.add(expr)
    for expr in sorted(undefaulted):
        problems.add(where, f"${{{expr}}} has no default (:-) nor a required marker (:?)")

    for name, svc in services.items():
        at = f"{where}: services.{name}"
        deps = svc.get("depends_on") or {}
        if isinstance(deps, list):
            deps = {d: {"condition": "service_started"} for d in deps}
        for dep, spec in deps.items():
            if dep not in services:
                problems.add(at, f"depends_on {dep}, which is not a service")
                continue
            condition = (spec or {}).get("condition", "service_started")
            target = services[dep]
            if condition == "service_healthy" and not target.get("healthcheck"):
                problems.add(at, f"waits for {dep} to be healthy, but {dep} has no healthcheck")
            if condition == "service_completed_successfully" and str(target.get("restart", "no")) != "no":
                problems.add(at, f"waits for {dep} to complete, but {dep} restarts ({target.get('restart')})")

        for port in svc.get("ports") or []:
            host = published_host_ip(port)
            if host is not None and host not in LOOPBACK:
                problems.add(at, f"port {port!r} is published beyond loopback")

        for mount in svc.get("volumes") or []:
            source = mount.get("source") if isinstance(mount, dict) else str(mount).split(":")[0]
            if source and not source.startswith((".", "/", "~", "$")) and source not in volumes:
                problems.add(at, f"volume {source} is not declared under volumes:")

        build = svc.get("build")
        if isinstance(build, dict):
            context = (path.parent / build.get("context", ".")).resolve()
            dockerfile = context / build.get("dockerfile", "Dockerfile")
            if not dockerfile.is_file():
                problems.add(at, f"build.dockerfile {dockerfile} does not exist")

        env = svc.get("environment") or {}
        if isinstance(env, list):
            env = dict(e.split("=", 1) if "=" in e else (e, None) for e in env)
        for key in env:
            check_env_key(key, schema, at, problems)
        command = svc.get("command")
        if isinstance(command, list) and "--role" in command:
            i = command.index("--role")
            if i + 1 >= len(command) or command[i + 1] not in ROLES:
                problems.add(at, f"--role needs one of {sorted(ROLES)}")


# --- k8s -------------------------------------------------------------------------------------


def load_manifests(directory: Path, files: list[str], problems: Problems) -> list[tuple[str, dict]]:
    """(path relative to the repository, document) for every document of files."""
    out = []
    for name in files:
        shown = str((directory / name).relative_to(DEPLOY.parent))
        for doc in yaml.safe_load_all((directory / name).read_text()):
            if doc is None:
                continue
            if not isinstance(doc, dict) or "kind" not in doc or "name" not in doc.get("metadata", {}):
                problems.add(shown, "a document without kind or metadata.name")
                continue
            out.append((shown, doc))
    return out


def matches(selector: dict, labels: dict) -> bool:
    return bool(selector) and all(labels.get(k) == v for k, v in selector.items())


def check_k8s(directory: Path, problems: Problems) -> None:
    where = str(directory.relative_to(DEPLOY.parent))
    kust = yaml.safe_load((directory / "kustomization.yaml").read_text())
    resources = kust.get("resources") or []
    present = sorted(p.name for p in directory.glob("*.yaml") if p.name != "kustomization.yaml")
    for name in resources:
        if not (directory / name).is_file():
            problems.add(f"{where}/kustomization.yaml", f"resource {name} does not exist")
    for name in present:
        if name not in resources:
            problems.add(f"{where}/kustomization.yaml", f"{name} is not listed under resources")
    docs = load_manifests(directory, [r for r in resources if (directory / r).is_file()], problems)
    by_kind: dict[str, dict[str, tuple[str, dict]]] = {}
    for file, doc in docs:
        by_kind.setdefault(doc["kind"], {})[doc["metadata"]["name"]] = (file, doc)

    schema = config_schema()
    grace = lookup(schema, ["server", "shutdown_grace_secs"])
    drain = lookup(schema, ["server", "shutdown_drain_secs"])
    for name, (file, cm) in by_kind.get("ConfigMap", {}).items():
        text = (cm.get("data") or {}).get("config.toml")
        if text is None:
            continue
        try:
            config = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            problems.add(file, f"config.toml in ConfigMap {name} is not TOML: {e}")
            continue
        check_toml_keys(config, schema, f"{file} (config.toml)", problems)
        grace = config.get("server", {}).get("shutdown_grace_secs", grace)
        drain = config.get("server", {}).get("shutdown_drain_secs", drain)
        if "role" in config.get("server", {}):
            problems.add(file, "server.role belongs to each Deployment's --role, not the shared config")
    for name, (file, secret) in by_kind.get("Secret", {}).items():
        for key in {**(secret.get("stringData") or {}), **(secret.get("data") or {})}:
            check_env_key(key, schema, f"{file}: Secret {name}", problems)

    images = {i.get("name") for i in kust.get("images") or []}
    deployments = by_kind.get("Deployment", {})
    roles_seen = set()
    for name, (file, dep) in deployments.items():
        at = f"{file}: Deployment {name}"
        spec = dep["spec"]
        pod = spec["template"]
        labels = pod["metadata"].get("labels") or {}
        if not matches(spec["selector"].get("matchLabels") or {}, labels):
            problems.add(at, "selector does not match the pod template's labels")
        pod_spec = pod["spec"]
        volumes = {v["name"]: v for v in pod_spec.get("volumes") or []}
        for v in volumes.values():
            if "configMap" in v and v["configMap"]["name"] not in by_kind.get("ConfigMap", {}):
                problems.add(at, f"volume {v['name']} names ConfigMap {v['configMap']['name']}, not in resources")
        for c in pod_spec["containers"]:
            image_name = c["image"].rsplit(":", 1)[0]
            if images and image_name not in images:
                problems.add(at, f"image {c['image']} is not rewritten by kustomization.yaml images")
            args = c.get("args") or []
            if "--role" in args:
                role = args[args.index("--role") + 1] if args.index("--role") + 1 < len(args) else ""
                if role not in ROLES:
                    problems.add(at, f"--role {role!r} is not one of {sorted(ROLES)}")
                roles_seen.add(role)
            for env_from in c.get("envFrom") or []:
                ref = (env_from.get("secretRef") or {}).get("name")
                if ref and ref not in by_kind.get("Secret", {}):
                    problems.add(at, f"envFrom names Secret {ref}, which is not in resources")
            for env in c.get("env") or []:
                check_env_key(env["name"], schema, at, problems)
            for m in c.get("volumeMounts") or []:
                if m["name"] not in volumes:
                    problems.add(at, f"volumeMount {m['name']} has no volume")
            ports = {p["containerPort"] for p in c.get("ports") or []} | {
                p.get("name") for p in c.get("ports") or []
            }
            for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
                spec_p = c.get(probe)
                if spec_p is None:
                    problems.add(at, f"no {probe}")
                    continue
                port = (spec_p.get("grpc") or spec_p.get("tcpSocket") or spec_p.get("httpGet") or {}).get("port")
                if port is not None and port not in ports:
                    problems.add(at, f"{probe} port {port} is not a container port")
            sc = c.get("securityContext") or {}
            if not sc.get("readOnlyRootFilesystem"):
                problems.add(at, "root filesystem is writable")
            pre_stop = 0
            cmd = (((c.get("lifecycle") or {}).get("preStop") or {}).get("exec") or {}).get("command") or []
            if len(cmd) == 2 and cmd[0] == "sleep" and cmd[1].isdigit():
                pre_stop = int(cmd[1])
            period = pod_spec.get("terminationGracePeriodSeconds", 30)
            if period <= pre_stop + drain + grace:
                problems.add(
                    at,
                    f"terminationGracePeriodSeconds {period} does not outlast preStop {pre_stop} s "
                    f"+ server.shutdown_drain_secs {drain} s + server.shutdown_grace_secs {grace} s",
                )
            readiness = c.get("readinessProbe") or {}
            noticed = readiness.get("periodSeconds", 10) * readiness.get("failureThreshold", 3)
            if "serve" in args and readiness and drain < noticed:
                problems.add(
                    at,
                    f"server.shutdown_drain_secs {drain} s is shorter than the readinessProbe takes to see "
                    f"NOT_SERVING (periodSeconds x failureThreshold = {noticed} s)",
                )
        if not (pod_spec.get("securityContext") or {}).get("runAsNonRoot"):
            problems.add(at, "pods may run as root")

    if not {"serve", "work"} <= roles_seen:
        problems.add(where, f"expected a serve and a work Deployment, found roles {sorted(roles_seen)}")

    def pods_selected(selector: dict) -> list[str]:
        return [n for n, (_, d) in deployments.items() if matches(selector, d["spec"]["template"]["metadata"]["labels"])]

    for name, (file, svc) in by_kind.get("Service", {}).items():
        selected = pods_selected(svc["spec"].get("selector") or {})
        if len(selected) != 1:
            problems.add(f"{file}: Service {name}", f"selects Deployments {selected}, expected exactly one")
            continue
        container_ports = set()
        for c in deployments[selected[0]][1]["spec"]["template"]["spec"]["containers"]:
            for p in c.get("ports") or []:
                container_ports |= {p["containerPort"], p.get("name")}
        for p in svc["spec"].get("ports") or []:
            if p.get("targetPort", p["port"]) not in container_ports:
                problems.add(f"{file}: Service {name}", f"targetPort {p.get('targetPort')} is not a container port")
    for name, (file, pdb) in by_kind.get("PodDisruptionBudget", {}).items():
        if len(pods_selected(pdb["spec"]["selector"].get("matchLabels") or {})) != 1:
            problems.add(f"{file}: PodDisruptionBudget {name}", "does not select exactly one Deployment")
    for name, (file, hpa) in by_kind.get("HorizontalPodAutoscaler", {}).items():
        ref = hpa["spec"]["scaleTargetRef"]
        if ref["kind"] != "Deployment" or ref["name"] not in deployments:
            problems.add(f"{file}: HorizontalPodAutoscaler {name}", f"targets {ref['kind']} {ref['name']}, not in resources")
            continue
        if "replicas" in deployments[ref["name"]][1]["spec"]:
            problems.add(f"{file}: HorizontalPodAutoscaler {name}", f"Deployment {ref['name']} sets replicas, which fights the HPA")
        uses_cpu = any(m.get("resource", {}).get("name") == "cpu" for m in hpa["spec"].get("metrics") or [])
        containers = deployments[ref["name"]][1]["spec"]["template"]["spec"]["containers"]
        if uses_cpu and not all((c.get("resources") or {}).get("requests", {}).get("cpu") for c in containers):
            problems.add(f"{file}: HorizontalPodAutoscaler {name}", "CPU utilisation needs CPU requests on every container")


# --- Dockerfile ------------------------------------------------------------------------------


def check_dockerfile(path: Path, problems: Problems) -> None:
    where = str(path.relative_to(DEPLOY.parent))
    schema = config_schema()
    # Join continuation lines, then read the KEY=VALUE pairs of ENV instructions.
    text = re.sub(r"\\\n", " ", path.read_text())
    for line in text.splitlines():
        if line.strip().upper().startswith("ENV "):
            for key in re.findall(r"(\w+)=", line):
                check_env_key(key, schema, where, problems)


def main(argv: list[str]) -> int:
    checks = {
        "compose": lambda p: check_compose(DEPLOY / "compose.yaml", p),
        "k8s": lambda p: check_k8s(DEPLOY / "k8s", p),
        "dockerfile": lambda p: check_dockerfile(DEPLOY / "Dockerfile", p),
    }
    names = argv or list(checks)
    unknown = [n for n in names if n not in checks]
    if unknown:
        print(f"unknown check(s) {unknown}; choose from {sorted(checks)}", file=sys.stderr)
        return 2
    problems = Problems()
    for name in names:
        checks[name](problems)
    for p in problems:
        print(p)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
