"""Every browser play recorded to MCAP (recorder) and the tab's Recordings folder with its replay."""
