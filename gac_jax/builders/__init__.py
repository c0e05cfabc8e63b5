"""Config -> model, anchors, priors, transforms and evaluators, for every user of a config
(trainers, evaluation, prediction, export)."""
