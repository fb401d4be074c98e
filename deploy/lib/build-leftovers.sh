# shellcheck shell=bash
# Sourced by deploy/build-images: removes what `buildah build` of deploy/Dockerfile leaves behind.
# buildah (1.28, Debian bookworm's) keeps a working container for each stage with no instruction
# of its own (`FROM ${BINARIES} AS binaries`, `FROM ${ORT} AS onnxruntime`), --rm and --force-rm
# notwithstanding, and each holds the untagged image of the stage under it (prebuilt,
# ortprebuilt: this build's binaries and ONNX Runtime). An image built again under its tag
# leaves its previous version untagged too. Without this, every build adds two containers and
# hundreds of MB of images that nothing uses.
#
#   leftovers_mark [IMAGE...]   before the build, with the images its stages start from: what
#                               exists then is not the build's to remove
#   leftovers_remove            after it, from an EXIT trap, so that a failed or interrupted
#                               build is cleaned up too
#
# Removed: the working containers made since the mark on untagged images or on the marked ones
# (a build killed mid-step leaves its steps' containers, on the base and on its cached layers),
# then the untagged images that appeared since. A container of a tagged image (a smoke test's or
# deploy/run's, of the image being rebuilt) is never touched, and an image a container still
# uses is kept: `buildah rmi` refuses it.

# Untagged images that are not a build's cached layers (those are `buildah images --all`'s).
_leftovers_untagged() {
  buildah images --quiet --no-trunc --filter dangling=true | sed 's/^sha256://'
}

leftovers_mark() {
  _leftovers_bases=("$@")
  _leftovers_images="$(_leftovers_untagged)"
  _leftovers_containers="$(buildah containers --all --quiet --noheading --notruncate)"
}

leftovers_remove() {
  local image id cimage name iname containers=0 images=0 bases=() removed=1
  # Resolved now: the base may have been made by the build itself.
  for image in "${_leftovers_bases[@]}"; do
    bases+=("$(buildah inspect --type image --format '{{.FromImageID}}' "$image" 2>/dev/null)")
  done
  # The build's working containers: on an untagged image (a stage's, or a cached step's) or on a
  # base, made since the mark. --all: a build killed mid-commit leaves one that is not buildah's
  # own (no builder mark) and that only --all lists.
  while read -r id cimage name iname; do
    grep -qxF "$id" <<<"${_leftovers_containers:-}" && continue
    case "$name" in *-working-container*) ;; *) continue ;; esac
    [ -z "$iname" ] || printf '%s\n' "${bases[@]}" | grep -qxF "$cimage" || continue
    buildah rm "$id" >/dev/null 2>&1 && containers=$((containers + 1))
  done < <(buildah containers --all --noheading --notruncate \
             --format '{{.ContainerID}} {{.ImageID}} {{.ContainerName}} {{.ImageName}}')
  # Until none is left: an interrupted stage's last layer gone, the one under it is untagged too.
  while [ "$removed" -gt 0 ]; do
    removed=0
    for image in $(_leftovers_untagged); do
      grep -qxF "$image" <<<"${_leftovers_images:-}" && continue
      buildah rmi "$image" >/dev/null 2>&1 && removed=$((removed + 1))
    done
    images=$((images + removed))
  done
  [ $((containers + images)) -eq 0 ] \
    || echo "build-images: removed what the build left: $containers working containers, $images untagged images"
}
