"""Data the project makes itself: correspondence sets and rendered D455 tabletop scenes."""
