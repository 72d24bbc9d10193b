"""Contact laws and contact geometry: each formula is written once here."""
