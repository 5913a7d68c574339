# Issue 62 (docs/campaign.md): Monte Carlo dispersion campaigns on the HIL rig, run on Ray.
#   make campaign                                  the first 40 missions of hil/campaigns/default.toml
#                                                  (truth navigation, 2 local workers: ~2 minutes on 2 cores)
#   make campaign CAMPAIGN_MISSIONS=1000           the whole campaign; run again to resume where it stopped
#   make campaign CAMPAIGN_NAV=cnn CAMPAIGN_MISSIONS=300   the CNN in the loop (~minutes per mission and core)
#   make campaign CAMPAIGN_ARGS="--address HEAD:6379"      on an existing Ray cluster (ray start / KubeRay)
# Folder: build/campaigns/default_<nav>/ (missions.parquet, report.md, figures/); one mission again:
#   python -m oibar_hil.campaign replay build/campaigns/default_truth INDEX
CAMPAIGN_PY       := PYTHONPATH=$(ROOT)/hil:$(ROOT)/host $(PY) -m oibar_hil.campaign
CAMPAIGN_CONFIG   ?= $(ROOT)/hil/campaigns/default.toml
CAMPAIGN_MISSIONS ?= 40
CAMPAIGN_NAV      ?= truth
CAMPAIGN_WORKERS  ?= 2
CAMPAIGN_ARGS     ?=

.PHONY: campaign

# Ray and pyarrow come with the campaign set-up profile (requirements/campaign.txt); no torch.
campaign: SETUP_PROFILE = campaign

campaign: firmware-host gen ## Monte Carlo dispersion campaign on Ray (CAMPAIGN_MISSIONS=40, CAMPAIGN_NAV=truth): success rate + bound, report in build/campaigns/
	@$(CAMPAIGN_PY) run --config $(CAMPAIGN_CONFIG) --name default_$(CAMPAIGN_NAV) --nav $(CAMPAIGN_NAV) \
	  --missions $(CAMPAIGN_MISSIONS) --workers $(CAMPAIGN_WORKERS) $(CAMPAIGN_ARGS)
