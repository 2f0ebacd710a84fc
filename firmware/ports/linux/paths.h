/*
 * The files a Linux program of the port is given (paths.c): no two flags may name one file, and
 * no one but root and this user may replace the NV record or a key file.
 */
#ifndef CANERGY_PORT_LINUX_PATHS_H
#define CANERGY_PORT_LINUX_PATHS_H

#include <stddef.h>

/* A file flag and its path (NULL: not given). */
struct port_file {
    const char *flag;
    const char *path;
};

/* Exit 2 (port_usage_error) when two of the count files given name one file: two spellings,
 * a symlink (dangling too, or through a linked directory) or a hard link. Reads nothing else and
 * creates nothing. */
void port_check_distinct(const struct port_file *files, size_t count);

/* Exit 2 (port_usage_error, naming flag, path, the directory and the fix) when someone other
 * than root and this user could replace or roll back path, as canergy.live.atomic's
 * check_private_dir (sshd's StrictModes): its directory, or one above it (as written, made
 * absolute, then once symlinks are resolved, then the directories of the file's own target when
 * path is a symlink), is writable by group or others without the sticky
 * bit (/tmp is fine), or belongs to another user. A directory that cannot be read is passed
 * over (the file's open fails later), and so is a NULL path (a flag not given). Only the
 * folders: the file itself is not looked at (a key file's mode is keyfile.c's, as keys.py's is
 * load_key's). Reads nothing else and creates nothing. */
void port_check_private_dir(const char *flag, const char *path);

#endif /* CANERGY_PORT_LINUX_PATHS_H */
