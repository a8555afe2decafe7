# The realistic suite's worlds, sourced by scripts/bench_realistic.sh (which
# builds and renders them) and by the benchmarks that render its flights
# again (bench_realism.sh, bench_seeds.sh): per world, the ortho and the DEM
# the camera's world is rendered from (the databases are built from a
# degraded copy of that DEM), and the options both take.
# shellcheck shell=bash disable=SC2034
real=data-samples/real
declare -A ortho dem
ortho[sierra]=$real/sierra-ortho-draped.tif; dem[sierra]=$real/sierra-dem.tif
ortho[saltlake]=$real/gsl-landsat7.tif;      dem[saltlake]=$real/gsl-dem-draped.tif
world_opts="--ortho-bands 3,2,1 --dem-vertical egm96"
