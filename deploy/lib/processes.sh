# shellcheck shell=bash
# Sourced by deploy/smoke-test and deploy/run: finding and signalling the processes a script
# started, through its own process tree. Never by name across the host (`pgrep -f`): another
# container of the same image, or a second replica, runs a process of the same name.
#
# `buildah run --isolation chroot` shares the host's PID namespace, and its process is not the
# container's init: it runs buildah-chroot-runtime, which runs buildah-chroot-exec, which runs
# the command. A SIGTERM to buildah kills the command outright (no drain) and orphans whatever
# it started, so the command itself is what gets the signal.
#
#   ours ROOT              ROOT is running and this shell's child: once a child has exited, its
#                          PID may be another process's, which nothing here may then touch
#   descendant ROOT NAME   the first process under ROOT, at any depth, named NAME (its comm)
#   signal_tree SIG ROOT   SIG to ROOT and to every process under it

ours() {
  local stat state parent
  stat="$(cat "/proc/$1/stat" 2>/dev/null)" || return 1
  # The fields after the name (which may hold spaces and parentheses): state, then parent; a
  # zombie (Z) has exited.
  read -r state parent _ <<<"${stat##*) }"
  [ "$state" != Z ] && [ "$parent" = "$$" ]
}

# Every process under ROOT, breadth first, from /proc (procps's pgrep need not be installed).
descendants() {
  local -A children=()
  local stat line pid state parent child queue=("$1")
  for stat in /proc/[0-9]*/stat; do
    # A process may end while this reads.
    read -r line 2>/dev/null <"$stat" || continue
    read -r state parent _ <<<"${line##*) }"
    children[$parent]+=" ${line%% *}"
  done
  while [ ${#queue[@]} -gt 0 ]; do
    pid="${queue[0]}"
    queue=("${queue[@]:1}")
    for child in ${children[$pid]:-}; do
      echo "$child"
      queue+=("$child")
    done
  done
}

descendant() {
  local pid
  ours "$1" || return 1
  for pid in $(descendants "$1"); do
    if [ "$(cat "/proc/$pid/comm" 2>/dev/null)" = "$2" ]; then
      echo "$pid"
      return 0
    fi
  done
  return 1
}

# The tree is listed before any signal, so that nothing reparented to init meanwhile is missed.
signal_tree() {
  local pid tree
  ours "$2" || return 0
  tree="$(descendants "$2")"
  for pid in $tree "$2"; do kill -s "$1" "$pid" 2>/dev/null || true; done
}
