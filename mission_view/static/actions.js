// Operator actions (filled in by the actions part of the view); nothing here yet.
