#!/usr/bin/env bash
# A new user's first hour, in one fresh virtual environment, with the README's two commands read
# out of README.md (the first ```bash block with more than `git clone` / `cd` lines: this runs
# in the checkout):
#   1. command 1 (a regular install and a first run); the run writes nothing into site-packages;
#      the same install made read-only and run by another user whose home is not writable
#      (compiles in memory, one line saying so) when this runs as root and can switch users;
#   2. command 2 (the test extra, editable, and the whole test suite) in the same venv; nothing
#      of the regular install is left to shadow the editable one: `cparticles --version` and
#      `import envs` (which registers the environments) work from another folder; gymnasium's
#      version is the one command 1 installed;
#   3. pip uninstall leaves nothing of the package in site-packages; reinstalled editable with
#      the test extra afterwards, for the rest of .ci/run.
# Usage: .ci/first_hour.sh VENV (created when missing; a fresh one is the point).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${1:?usage: .ci/first_hour.sh VENV}
[ -e "$VENV" ] || python -m venv "$VENV"
export PATH="$VENV/bin:$PATH"
ELSEWHERE=$(mktemp -d)  # "another folder": not the checkout
chmod 755 "$ELSEWHERE"
SITE=$(python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
as_nobody() { setpriv --reuid="$(id -u nobody)" --regid="$(id -g nobody)" --clear-groups "$@"; }
say() { printf '\n== first hour: %s (%s)\n' "$*" "$(date +%T)"; }
fail() { printf 'FAIL first hour: %s\n' "$*" >&2; exit 1; }

mapfile -t COMMANDS < <(python - <<'EOF'
import re
text = open("README.md", encoding="utf-8").read()
for block in re.finditer(r"^```bash\n(.*?)^```", text, re.M | re.S):
    lines = [line.strip() for line in block.group(1).splitlines()]
    lines = [line for line in lines
             if line and not line.startswith(("#", "git clone ", "cd "))]
    if lines:  # the first bash block with more than the clone step
        print("\n".join(lines))
        break
EOF
)
[ "${#COMMANDS[@]}" -eq 2 ] || fail "README's first bash block of commands should hold 2, found: ${COMMANDS[*]}"
for c in "${COMMANDS[@]}"; do
    [[ "$c" == "python -m pip install "*" && "* ]] || fail "not 'python -m pip install ... && ...': $c"
done

# Files in site-packages newer than the marker $1 (written by whatever ran since).
written_since() { find "$SITE" -newer "$1" -print; }
# What is left in site-packages of the package: its folders, dist-info, editable hooks.
leftovers() {
    find "$SITE" -maxdepth 1 \( -name constrained_particles -o -name envs -o -name verification \
        -o -name cparticles -o -iname '*constrained_particles*' \) -print
}

say "command 1: ${COMMANDS[0]}"
install1=${COMMANDS[0]%% && *}
run1=${COMMANDS[0]#* && }
bash -c "$install1"
gym_after_1=$(python -c 'import gymnasium; print(gymnasium.__version__)')
marker=$(mktemp); sleep 1
bash -c "$run1"
new=$(written_since "$marker")
[ -z "$new" ] || fail "command 1's run wrote into site-packages:"$'\n'"$new"

say "read-only install, run by a user whose home is not writable"
if [ "$(id -u)" = 0 ] && id nobody >/dev/null 2>&1 && command -v setpriv >/dev/null \
        && as_nobody "$VENV/bin/python" -c pass 2>/dev/null; then
    chmod -R a-w "$SITE"
    set +e
    (cd "$ELSEWHERE" && as_nobody env -u XDG_CACHE_HOME -u NUMBA_CACHE_DIR HOME=/nonexistent \
        cparticles demo --env ClothSlide-v0 --agent scripted --episodes 1 --seed 0) \
        2>"$ELSEWHERE/stderr"
    status=$?
    set -e
    chmod -R u+w "$SITE"
    cat "$ELSEWHERE/stderr" >&2
    [ "$status" = 0 ] || fail "demo as nobody on a read-only install exited $status"
    [ "$(grep -c '^constrained-particles: cache directory' "$ELSEWHERE/stderr")" = 1 ] \
        || fail "expected one line saying the kernels compile in memory"
else
    echo "SKIPPED (not checked): needs root, user nobody, setpriv, and a venv interpreter nobody can run"
fi

say "command 2: ${COMMANDS[1]}"
install2=${COMMANDS[1]%% && *}
run2=${COMMANDS[1]#* && }
bash -c "$install2"
left=$(leftovers | grep -v -e '__editable__' -e '\.dist-info$' || true)
[ -z "$left" ] || fail "the regular install left files that shadow the editable one:"$'\n'"$left"
marker=$(mktemp); sleep 1
bash -c "$run2"
new=$(written_since "$marker")
[ -z "$new" ] || fail "command 2's run wrote into site-packages:"$'\n'"$new"
gym_after_2=$(python -c 'import gymnasium; print(gymnasium.__version__)')
[ "$gym_after_1" = "$gym_after_2" ] \
    || fail "gymnasium $gym_after_1 after command 1 but $gym_after_2 after command 2"

say "from another folder ($ELSEWHERE)"
(cd "$ELSEWHERE" && cparticles --version)
(cd "$ELSEWHERE" && python -c "
import gymnasium as gym
import envs
for env_id in envs.ENV_IDS:
    gym.make(env_id).close()
print('registered:', ', '.join(envs.ENV_IDS))")

say "pip uninstall leaves nothing behind"
python -m pip uninstall --yes constrained-particles
left=$(leftovers)
[ -z "$left" ] || fail "pip uninstall left:"$'\n'"$left"
python -m pip install --quiet --no-deps -e .
rm -rf "$ELSEWHERE" "$marker"
say "all checks passed (gymnasium $gym_after_2)"
