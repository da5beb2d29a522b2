# Sourced by .ci/run: start a throwaway PostgreSQL 15 for the gallery's storage tests and export
# KINETIX_TEST_POSTGRES_URL. Idempotent: a server already started by this script (same data dir) is reused.
# PostgreSQL refuses to run as root, so the cluster belongs to an unprivileged user.
PG_TEST_USER="${PG_TEST_USER:-kinetixpg}"
PG_TEST_PORT="${PG_TEST_PORT:-54329}"
PG_TEST_DIR="${PG_TEST_DIR:-/tmp/kinetix-pg-test}"
PG_TEST_DB="kinetix_test"

_pg_setup() {
    local run=()
    if ! command -v initdb >/dev/null || ! command -v pg_ctl >/dev/null; then
        if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
            apt-get update -qq && apt-get install -y -qq postgresql >/dev/null
            local bindir
            bindir="$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -1)"
            [ -n "$bindir" ] && PATH="$bindir:$PATH"
        fi
        command -v initdb >/dev/null || { echo "setup-postgres: initdb not found" >&2; return 1; }
    fi
    if [ "$(id -u)" = 0 ]; then
        id -u "$PG_TEST_USER" >/dev/null 2>&1 || useradd --system --no-create-home --shell /usr/sbin/nologin "$PG_TEST_USER"
        run=(runuser -u "$PG_TEST_USER" --)
        mkdir -p "$PG_TEST_DIR" && chown "$PG_TEST_USER" "$PG_TEST_DIR"
    else
        mkdir -p "$PG_TEST_DIR"
    fi
    if [ ! -f "$PG_TEST_DIR/data/PG_VERSION" ]; then
        "${run[@]}" initdb -D "$PG_TEST_DIR/data" -U postgres --auth=trust -E UTF8 >/dev/null || return 1
    fi
    mkdir -p "$PG_TEST_DIR/socket" && [ "$(id -u)" != 0 ] || chown "$PG_TEST_USER" "$PG_TEST_DIR/socket"
    if ! "${run[@]}" pg_ctl -D "$PG_TEST_DIR/data" status >/dev/null 2>&1; then
        "${run[@]}" pg_ctl -D "$PG_TEST_DIR/data" -l "$PG_TEST_DIR/log" -w -t 60 \
            -o "-p $PG_TEST_PORT -k $PG_TEST_DIR/socket -c listen_addresses=127.0.0.1 -c max_connections=200" \
            start >/dev/null || { cat "$PG_TEST_DIR/log" >&2; return 1; }
        PG_TEST_STARTED=1
    fi
    if ! "${run[@]}" psql -h 127.0.0.1 -p "$PG_TEST_PORT" -U postgres -Atc \
            "SELECT 1 FROM pg_database WHERE datname = '$PG_TEST_DB'" postgres | grep -q 1; then
        "${run[@]}" createdb -h 127.0.0.1 -p "$PG_TEST_PORT" -U postgres "$PG_TEST_DB" || return 1
    fi
    export KINETIX_TEST_POSTGRES_URL="postgresql://postgres@127.0.0.1:$PG_TEST_PORT/$PG_TEST_DB"
    PG_TEST_RUN=("${run[@]}")
}

_pg_stop() {
    "${PG_TEST_RUN[@]}" pg_ctl -D "$PG_TEST_DIR/data" -m fast stop >/dev/null 2>&1 || true
}

if _pg_setup; then
    # Stop it when .ci/run exits, but only if this shell started it.
    if [ "${PG_TEST_STARTED:-0}" = 1 ]; then
        # Keep any EXIT trap another setup script registered.
        _pg_prev_trap="$(trap -p EXIT | sed -E "s/^trap -- '(.*)' EXIT$/\1/")"
        trap "_pg_stop; ${_pg_prev_trap}" EXIT
    fi
    echo "setup-postgres: $KINETIX_TEST_POSTGRES_URL"
else
    echo "setup-postgres: could not start PostgreSQL; the gallery's PostgreSQL tests will fail in CI" >&2
fi
