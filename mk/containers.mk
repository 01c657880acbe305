# Container image and cluster targets (included by the Makefile; docs/hpc.md).
# None of them runs in `make test`: they need buildah/podman/docker, slurm-wlm,
# and the package index for the wheelhouse.
#
# image, image-check and image-archive use the first builder that works of
# buildah, podman and docker (docker only when its daemon answers) and say which;
# when none works they install buildah and mmdebstrap from Debian (apt-get, as
# root or through sudo), as `make setup` installs WSClean (scripts/container-lib.sh).
#
#   make image          wheelhouse + base + build of docker/Dockerfile, tagged as
#                       cabs/images.yml names it (scripts/image-build.sh)
#   make image-check    the demo recipe inside the image vs on the host: same numbers
#   make image-archive  docker-archive tarball of the image (input of apptainer build)
#   make image-sif      hitops.sif with Apptainer, from that archive (needs apptainer)
#   make slurm-check    a one-node slurm cluster: the demo through srun, and
#                       hitops calibrate --scheduler slurm (dask-jobqueue)
#
# Build artefacts go to $(HITOPS_BUILD_CACHE) (default /var/tmp/hitops-build),
# outside the repository.

HITOPS_BUILD_CACHE ?= /var/tmp/hitops-build
export HITOPS_BUILD_CACHE
# the environment the wheelhouse copies (versions) and the host runs use
HITOPS_PYTHON ?= $(abspath $(PY))
export HITOPS_PYTHON

.PHONY: image image-check image-archive image-sif slurm-check

image: $(STAMP) ## build the container image offline from a wheelhouse (buildah/podman/docker; installs buildah+mmdebstrap when none works; docs/hpc.md)
	scripts/image-build.sh

image-check: $(STAMP) wsclean casa-config ## run the demo inside the image and on the host: same peak-flux numbers
	scripts/image-check.sh

image-archive: ## write the image as a docker-archive tarball (for docker load / apptainer build)
	scripts/image-archive.sh

image-sif: image-archive ## build hitops.sif from that archive with Apptainer (needs apptainer)
	scripts/image-archive.sh --sif

slurm-check: $(STAMP) wsclean casa-config ## one-node slurm cluster: the demo through srun, calibrate --scheduler slurm
	scripts/slurm-check.sh
