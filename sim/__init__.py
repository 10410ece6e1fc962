"""bess-ded simulation side: plant, energy router, scenarios, runners, reference, CLI."""
