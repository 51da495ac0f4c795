"""The synthetic house: scripted people rendered into every camera, with exact ground truth."""
