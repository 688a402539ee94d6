# Sourced by the job scripts that run the Makefile's chain in a variant RUN V =
# runs/experiment-s<SEED>/variants/<NAME> beside the seed's RUN (budget_job.sh, long_retrain_job.sh,
# score_job.sh, truth_job.sh, x2_long_job.sh, target_share_job.sh LABELS=cut06).
#   link_variant V [PART ...]: V/data, V/library and V/iter0 link the seed's; V/iter1/PART links
#     the seed's iter1/PART (e.g. ptsn pseudo rc cf), so make finds them up to date
#   ppcg_variant NAME (needs R and SEED): V=$R/variants/NAME linked to the seed's iteration-1
#     ptsn, pseudo, rc and cf; O=runs/val800/experiment-s$SEED/NAME, where its rows' evaluations
#     on val800_job.sh's 800 fresh frames go
link_variant() {
    local v=$1 shared part; shift
    mkdir -p $v/iter1
    for shared in data library iter0; do ln -sfn ../../$shared $v/$shared; done
    for part in "$@"; do ln -sfn ../../../iter1/$part $v/iter1/$part; done
}
ppcg_variant() {
    V=$R/variants/$1
    O=runs/val800/experiment-s$SEED/$1
    link_variant $V ptsn pseudo rc cf
}
