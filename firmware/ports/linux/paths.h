/*
 * The files a Linux program of the port is given (paths.c): no two flags may name one file.
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

#endif /* CANERGY_PORT_LINUX_PATHS_H */
