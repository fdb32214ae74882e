"""The site's fleet view: every robot of a site on the shared map, goals and pose lists to one robot at a time."""
