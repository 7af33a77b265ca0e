#!/usr/bin/env bash
# Validates the deployment files without a container engine or a cluster, offline:
#   hadolint              deploy/Dockerfile (fails on warnings and errors)
#   yamllint              every YAML file under deploy/ (deploy/.yamllint, strict)
#   kubernetes-validate   deploy/k8s manifests against Kubernetes $K8S_VERSION's schemas, strict
#                         (unknown fields are errors)
#   compose-spec          deploy/compose.yaml against the compose-spec JSON schema
#                         (check-jsonschema's vendored copy)
#   cross-file checks     deploy/checks.py: references between services, manifests and
#                         kustomization.yaml, loopback-only ports, and every configuration key
#                         used checked against deploy/config.example.toml
# The tools come from tests/python/requirements-deploy.txt, installed into .venv once per
# version of that file. Prints one line per check and a count; exits 1 if any failed.
set -uo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.." || exit 1

VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}
K8S_VERSION=${K8S_VERSION:-1.31.0}
REQUIREMENTS=tests/python/requirements-deploy.txt

if [[ ! -x $VENV/bin/python ]]; then
    "$PYTHON" -m venv "$VENV" || exit 1
fi
stamp="$VENV/.deploy-tools-$(sha256sum "$REQUIREMENTS" | cut -d' ' -f1)"
if [[ ! -e $stamp ]]; then
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-cache-dir -r "$REQUIREMENTS" || exit 1
    rm -f "$VENV"/.deploy-tools-*
    touch "$stamp"
fi
bin=$VENV/bin

passed=0
failed=0
# run NAME COMMAND...: runs one check and prints its summary line, then its output indented.
run() {
    local name=$1 out status
    shift
    out=$("$@" 2>&1)
    status=$?
    if ((status == 0)); then
        echo "deploy: $name: ok"
        passed=$((passed + 1))
    else
        echo "deploy: $name: FAILED (exit $status)"
        failed=$((failed + 1))
    fi
    if [[ -n $out ]]; then
        printf '    %s\n' "${out//$'\n'/$'\n'    }"
    fi
}

k8s_manifests=()
for f in deploy/k8s/*.yaml; do
    # kustomization.yaml is no Kubernetes object (checks.py covers it).
    [[ $f == */kustomization.yaml ]] || k8s_manifests+=("$f")
done

run "hadolint deploy/Dockerfile" \
    "$bin/hadolint" --no-color --failure-threshold warning deploy/Dockerfile
run "yamllint deploy/" \
    "$bin/yamllint" --strict -c deploy/.yamllint deploy/
run "kubernetes-validate deploy/k8s (Kubernetes $K8S_VERSION, strict)" \
    "$bin/kubernetes-validate" --strict --quiet -k "$K8S_VERSION" "${k8s_manifests[@]}"
run "compose-spec schema deploy/compose.yaml" \
    "$bin/check-jsonschema" --quiet --builtin-schema vendor.compose-spec deploy/compose.yaml
run "cross-file checks (compose, k8s, Dockerfile)" \
    "$bin/python" deploy/checks.py compose k8s dockerfile

echo "deploy: $passed passed, $failed failed"
((failed == 0))
