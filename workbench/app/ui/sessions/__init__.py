"""The Sessions tab: save, list and load sessions."""
