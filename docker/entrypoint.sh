#!/bin/sh
# Container entry: run edi-live, publishing on $EDI_LIVE_CONTAINER_PUBLISH (tcp://0.0.0.0:5555) unless the
# arguments already choose (--publish, --no-publish) or only ask for information (--help, --version,
# --list-devices). `exec` makes edi-live the process that receives SIGTERM from `docker stop`.
set -eu
for arg in "$@"; do
    case "$arg" in
        --publish|--publish=*|--no-publish|-h|--help|--version|--list-devices) exec edi-live "$@" ;;
    esac
done
exec edi-live --publish "${EDI_LIVE_CONTAINER_PUBLISH:-tcp://0.0.0.0:5555}" "$@"
