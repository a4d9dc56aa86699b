#!/usr/bin/env bash
# A private PostgreSQL server for the distributed-study tests: `start` installs it if missing,
# initialises a throw-away cluster on a loopback port and prints the export line for
# TORCHCAL_TEST_PG_URL; `stop DIR` stops it and removes its data. Needs root (apt-get, su).
set -euo pipefail
PORT="${TORCHCAL_PG_PORT:-55432}"

bin_dir() { ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -n 1; }

case "${1:-}" in
  start)
    if [ -z "$(bin_dir)" ]; then
      apt-get update -qq >&2
      DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql >&2
    fi
    BIN="$(bin_dir)"
    DATA="$(mktemp -d /tmp/torchcal-pg.XXXXXX)"
    chown postgres "$DATA"
    su postgres -s /bin/sh -c "$BIN/initdb -D $DATA -A trust -U postgres" >/dev/null
    su postgres -s /bin/sh -c "$BIN/pg_ctl -D $DATA -l $DATA/server.log -w -o '-p $PORT -k $DATA -c listen_addresses=127.0.0.1' start" >/dev/null
    su postgres -s /bin/sh -c "$BIN/createdb -h 127.0.0.1 -p $PORT -U postgres torchcal_test"
    echo "$DATA"
    ;;
  stop)
    DATA="$2"
    su postgres -s /bin/sh -c "$(bin_dir)/pg_ctl -D $DATA -m fast -w stop" >/dev/null || true
    rm -rf "$DATA"
    ;;
  *)
    echo "usage: $0 start | stop DIR" >&2
    exit 2
    ;;
esac
