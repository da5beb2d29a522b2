# Sourced by .ci/run: make sure nginx (Debian's package) is installed for the deployment test
# (tests/deploy/test_two_processes.py runs it as an unprivileged foreground process on 127.0.0.1 with its own
# config; the system service is not used). Idempotent: nothing happens when nginx is there already.
_nginx_setup() {
    command -v nginx >/dev/null && return 0
    [ -x /usr/sbin/nginx ] && return 0
    if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
        # policy-rc.d: the package must not start the system nginx on port 80 (the test starts its own).
        local policy=/usr/sbin/policy-rc.d created=0
        if [ ! -e "$policy" ]; then
            printf '#!/bin/sh\nexit 101\n' >"$policy" && chmod +x "$policy" && created=1
        fi
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq nginx >/dev/null
        [ "$created" = 1 ] && rm -f "$policy"
    fi
    command -v nginx >/dev/null || [ -x /usr/sbin/nginx ] || { echo "setup-nginx: nginx not found" >&2; return 1; }
}
_nginx_setup || echo "setup-nginx: the deployment test will fail (CI) or skip without nginx" >&2
unset -f _nginx_setup
