#!/usr/bin/env bash
# Headless Chromium for the browser end-to-end tests (tests/e2e) and `kinetix bench server`.
# Idempotent: installs the apt package only when /usr/bin/chromium is missing (apt-get needs root).
if [ ! -x /usr/bin/chromium ]; then
    if [ "$(id -u)" = "0" ]; then _kinetix_sudo=""; else _kinetix_sudo="sudo"; fi
    $_kinetix_sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $_kinetix_sudo apt-get install -y -qq chromium >/dev/null
    unset _kinetix_sudo
fi
export KINETIX_CHROMIUM=/usr/bin/chromium
