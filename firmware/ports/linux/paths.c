/*
 * Two names for one file (ports/linux, both programs), as canergy.live.atomic.same_file: the same
 * inode when both exist (hard links too), otherwise the same path once symlinks are resolved.
 * A file's folders no one else may write, as canergy.live.atomic.check_private_dir: the NV
 * record's and the key files'.
 */
#define _GNU_SOURCE 1

#include "paths.h"

#include "args.h"

#include <errno.h>
#include <libgen.h>
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

/* dst = src, or a usage error naming what was too long. */
static void copy_path(char dst[PATH_MAX], const char *src)
{
    if (snprintf(dst, PATH_MAX, "%s", src) >= PATH_MAX) {
        port_usage_error("path too long: %.64s...", src);
    }
}

/* dst = "dir/name" ("/name" when dir is "/"), or a usage error naming what was too long. */
static void join_path(char dst[PATH_MAX], const char *dir, const char *name)
{
    const char *sep = strcmp(dir, "/") == 0 ? "" : "/";
    if (snprintf(dst, PATH_MAX, "%s%s%s", dir, sep, name) >= PATH_MAX) {
        port_usage_error("path too long: %.64s...", name);
    }
}

/* A path that does not exist: its resolved directory and its last part (as written when the
 * directory does not exist either: nothing can be created there). */
static void resolve_missing(const char *p, char out[PATH_MAX])
{
    char dir[PATH_MAX];
    char base[PATH_MAX];
    char real_dir[PATH_MAX];
    copy_path(dir, p);
    copy_path(base, p);
    if (realpath(dirname(dir), real_dir) == NULL) {
        copy_path(out, p);
    } else {
        join_path(out, real_dir, basename(base));
    }
}

/* path's file once symlinks are resolved, as Python's Path.resolve(): a missing file (the target
 * of a dangling symlink too) is named below its resolved directory. */
static void resolve(const char *path, char out[PATH_MAX])
{
    char p[PATH_MAX];
    copy_path(p, path);
    for (int hops = 0; hops < 40; hops++) {
        if (realpath(p, out) != NULL) {
            return;
        }
        char target[PATH_MAX];
        const ssize_t n = readlink(p, target, sizeof target - 1U);
        if (n < 0) { /* not a symlink: missing */
            resolve_missing(p, out);
            return;
        }
        target[n] = '\0';
        char dir[PATH_MAX];
        copy_path(dir, p);
        if (target[0] == '/') {
            copy_path(p, target);
        } else {
            join_path(p, dirname(dir), target);
        }
    }
    copy_path(out, p); /* a symlink loop: as written */
}

/* a and b name one file: the same inode when both exist (hard links too), otherwise the same
 * path once resolved. */
static int same_file(const char *a, const char *b)
{
    struct stat sa;
    struct stat sb;
    if (stat(a, &sa) == 0 && stat(b, &sb) == 0) {
        return sa.st_dev == sb.st_dev && sa.st_ino == sb.st_ino;
    }
    char ra[PATH_MAX];
    char rb[PATH_MAX];
    resolve(a, ra);
    resolve(b, rb);
    return strcmp(ra, rb) == 0;
}

void port_check_distinct(const struct port_file *files, size_t count)
{
    for (size_t i = 0U; i < count; i++) {
        for (size_t j = 0U; j < i; j++) {
            if (files[i].path != NULL && files[j].path != NULL &&
                same_file(files[j].path, files[i].path)) {
                port_usage_error("%s %s and %s %s name the same file; give each its own path",
                                 files[j].flag, files[j].path, files[i].flag, files[i].path);
            }
        }
    }
}

/* out = path made absolute and normalized as written, as Python's os.path.abspath: "." and
 * empty parts dropped, ".." taking the part before it away (symlinks are not followed). */
static void absolute(const char *path, char out[PATH_MAX])
{
    char whole[PATH_MAX];
    if (path[0] == '/') {
        copy_path(whole, path);
    } else {
        char cwd[PATH_MAX];
        if (getcwd(cwd, sizeof cwd) == NULL) {
            port_usage_error("%s: cannot read the current directory: %s", path, strerror(errno));
        }
        join_path(whole, cwd, path);
    }
    size_t len = 0U;
    out[0] = '\0';
    for (char *save = NULL, *part = strtok_r(whole, "/", &save); part != NULL;
         part = strtok_r(NULL, "/", &save)) {
        if (strcmp(part, ".") == 0) {
            continue;
        }
        if (strcmp(part, "..") == 0) {
            while (len > 0U && out[len - 1U] != '/') {
                len--;
            }
            len = len > 0U ? len - 1U : 0U; /* the '/' before it */
            out[len] = '\0';
            continue;
        }
        const size_t n = strlen(part);
        if (len + 1U + n >= PATH_MAX) {
            port_usage_error("path too long: %.64s...", path);
        }
        out[len++] = '/';
        memcpy(&out[len], part, n + 1U);
        len += n;
    }
    if (len == 0U) {
        copy_path(out, "/");
    }
}

/* folder and every directory above it, checked in turn (see port_check_private_dir). */
static void check_folders(const char *flag, const char *path, const char *folder)
{
    char d[PATH_MAX];
    copy_path(d, folder);
    for (;;) {
        struct stat st;
        if (stat(d, &st) == 0) {
            if (st.st_uid != 0U && st.st_uid != geteuid()) {
                port_usage_error("%s %s: directory %s belongs to user %lu, who can replace or "
                                 "roll back the file; use a directory of root's or your own",
                                 flag, path, d, (unsigned long)st.st_uid);
            }
            if ((st.st_mode & (S_IWGRP | S_IWOTH)) != 0U && (st.st_mode & S_ISVTX) == 0U) {
                port_usage_error("%s %s: directory %s (mode %04o) is writable by others, who can "
                                 "replace or roll back the file; chmod go-w %s",
                                 flag, path, d, (unsigned)(st.st_mode & 07777U), d);
            }
        }
        if (strcmp(d, "/") == 0) {
            return;
        }
        char up[PATH_MAX];
        copy_path(up, d);
        copy_path(d, dirname(up));
    }
}

void port_check_private_dir(const char *flag, const char *path)
{
    if (path == NULL) { /* the flag was not given */
        return;
    }
    char abs[PATH_MAX];
    absolute(path, abs);
    char file[PATH_MAX]; /* the file's own symlinks followed: a key linked into an open folder */
    resolve(abs, file);
    char folder[PATH_MAX];
    copy_path(folder, dirname(abs)); /* abs is the folder from here on (libgen's dirname) */
    check_folders(flag, path, folder);
    char real[PATH_MAX];
    if (realpath(folder, real) != NULL) {
        check_folders(flag, path, real);
    }
    check_folders(flag, path, dirname(file));
}
