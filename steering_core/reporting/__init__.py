"""What people look at: progress bars and callbacks (`progress`), terminal tables (`tables`), PNG plots (`plots`)."""
