/* rlbridge.wire._chacha: ChaCha20-Poly1305 (IETF, RFC 8439) from libsodium, for sealing.
 *
 * Why this exists: a value sealed at 1 kHz meets cold caches at each of the four AEAD calls
 * on its way (publisher seals, server opens and seals, subscriber opens). `cryptography`
 * copies a fresh OpenSSL cipher context per call and sets the nonce, the associated data and
 * the tag through OpenSSL's provider calls; cold, that set-up costs about twice what
 * libsodium's one function call does (docs/benchmarks.md, "Cost of encryption"). The
 * construction is the same (RFC 8439 section 2.8), so either side may use either library:
 * rlbridge.wire.aead chooses, and falls back to `cryptography` when this was not built.
 *
 * Deliberately small: no cryptography here, only argument checks, buffers and the two
 * libsodium calls. The API mirrors cryptography's ChaCha20Poly1305 (encrypt/decrypt with
 * nonce, data, associated_data; a tag that does not verify raises
 * cryptography.exceptions.InvalidTag), so the callers do not know which one they hold, plus
 * the two calls rlbridge's records and datagrams make (seal_counted/open_counted: the nonce
 * made from a counter, the associated data the bytes before the ciphertext), each one
 * allocation and no slicing, which rlbridge.wire.aead gives cryptography's class too.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <sodium.h>

#define KEY_BYTES crypto_aead_chacha20poly1305_ietf_KEYBYTES
#define NONCE_BYTES crypto_aead_chacha20poly1305_ietf_NPUBBYTES
#define TAG_BYTES crypto_aead_chacha20poly1305_ietf_ABYTES
/* The GIL stays held: releasing and taking it back costs more than sealing a datagram, and
 * the largest message, a 64 KiB TCP record (wire/records.py), takes tens of microseconds. */

/* cryptography.exceptions.InvalidTag, looked up once at import and never changed. */
static PyObject *invalid_tag;

typedef struct {
    PyObject_HEAD
    unsigned char key[KEY_BYTES];
    int keyed;  /* __init__ took a key (an object made by __new__ alone has none) */
} Aead;

static int
aead_init(Aead *self, PyObject *args, PyObject *kwargs)
{
    static char *keywords[] = {"key", NULL};
    Py_buffer key;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "y*:ChaCha20Poly1305", keywords, &key))
        return -1;
    if (key.len != KEY_BYTES) {
        PyBuffer_Release(&key);
        PyErr_SetString(PyExc_ValueError, "ChaCha20Poly1305 key must be 32 bytes.");
        return -1;
    }
    memcpy(self->key, key.buf, KEY_BYTES);
    PyBuffer_Release(&key);
    self->keyed = 1;
    return 0;
}

static void
aead_dealloc(Aead *self)
{
    sodium_memzero(self->key, KEY_BYTES);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Every method: the object has a key, and the call gives three arguments (named in
 * `signature`, for the error). */
static int
check_call(const Aead *self, Py_ssize_t nargs, const char *signature)
{
    if (!self->keyed) {
        PyErr_SetString(PyExc_ValueError, "ChaCha20Poly1305 was not given a key");
        return -1;
    }
    if (nargs != 3) {
        PyErr_Format(PyExc_TypeError, "%s takes 3 arguments, %zd given", signature, nargs);
        return -1;
    }
    return 0;
}

/* The three arguments as buffers: the nonce (12 bytes), the data and the associated data
 * (None: none). On success every buffer is held and must be released (release_args). */
static int
get_args(Aead *self, PyObject *const *args, Py_ssize_t nargs, const char *signature,
         Py_buffer *nonce, Py_buffer *data, Py_buffer *aad)
{
    if (check_call(self, nargs, signature) < 0)
        return -1;
    if (PyObject_GetBuffer(args[0], nonce, PyBUF_SIMPLE) < 0)
        return -1;
    if (nonce->len != NONCE_BYTES) {
        PyBuffer_Release(nonce);
        PyErr_SetString(PyExc_ValueError, "Nonce must be 12 bytes");
        return -1;
    }
    if (PyObject_GetBuffer(args[1], data, PyBUF_SIMPLE) < 0) {
        PyBuffer_Release(nonce);
        return -1;
    }
    if (args[2] == Py_None) {
        aad->obj = NULL;
        aad->buf = NULL;
        aad->len = 0;
    }
    else if (PyObject_GetBuffer(args[2], aad, PyBUF_SIMPLE) < 0) {
        PyBuffer_Release(nonce);
        PyBuffer_Release(data);
        return -1;
    }
    return 0;
}

static void
release_args(Py_buffer *nonce, Py_buffer *data, Py_buffer *aad)
{
    PyBuffer_Release(nonce);
    PyBuffer_Release(data);
    if (aad->obj != NULL)
        PyBuffer_Release(aad);
}

/* Seal data into out (ciphertext, then the tag: the combined form's layout). */
static void
seal_into(const Aead *self, unsigned char *out, const Py_buffer *nonce, const Py_buffer *data,
          const Py_buffer *aad)
{
    crypto_aead_chacha20poly1305_ietf_encrypt_detached(
        out, out + data->len, NULL, data->buf, (unsigned long long)data->len, aad->buf,
        (unsigned long long)aad->len, NULL, nonce->buf, self->key);
}

/* Open sealed data (ciphertext, then the tag) into out; nonzero if the tag does not verify. */
static int
open_into(const Aead *self, unsigned char *out, const Py_buffer *nonce, const Py_buffer *data,
          const Py_buffer *aad)
{
    const unsigned char *sealed = data->buf;
    size_t plain_len = (size_t)data->len - TAG_BYTES;
    return crypto_aead_chacha20poly1305_ietf_decrypt_detached(
        out, NULL, sealed, (unsigned long long)plain_len, sealed + plain_len, aad->buf,
        (unsigned long long)aad->len, nonce->buf, self->key);
}

static PyObject *
aead_encrypt(Aead *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer nonce, data, aad;
    if (get_args(self, args, nargs, "encrypt(nonce, data, associated_data)", &nonce, &data,
                 &aad) < 0)
        return NULL;
    PyObject *out = NULL;
    if (data.len > PY_SSIZE_T_MAX - TAG_BYTES) {
        PyErr_SetString(PyExc_OverflowError, "data too long to encrypt");
        goto done;
    }
    out = PyBytes_FromStringAndSize(NULL, data.len + TAG_BYTES);
    if (out == NULL)
        goto done;
    unsigned char *sealed = (unsigned char *)PyBytes_AS_STRING(out);
    seal_into(self, sealed, &nonce, &data, &aad);
done:
    release_args(&nonce, &data, &aad);
    return out;
}

static PyObject *
aead_decrypt(Aead *self, PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer nonce, data, aad;
    if (get_args(self, args, nargs, "decrypt(nonce, data, associated_data)", &nonce, &data,
                 &aad) < 0)
        return NULL;
    PyObject *out = NULL;
    if (data.len < TAG_BYTES) {
        PyErr_SetNone(invalid_tag);
        goto done;
    }
    Py_ssize_t plain_len = data.len - TAG_BYTES;
    out = PyBytes_FromStringAndSize(NULL, plain_len);
    if (out == NULL)
        goto done;
    unsigned char *plain = (unsigned char *)PyBytes_AS_STRING(out);
    /* libsodium verifies before it decrypts: nothing unverified escapes */
    if (open_into(self, plain, &nonce, &data, &aad) != 0) {
        Py_CLEAR(out);
        PyErr_SetNone(invalid_tag);
    }
done:
    release_args(&nonce, &data, &aad);
    return out;
}

/* The nonce of a record or datagram counter: 4 zero bytes, then the counter (u64 big-endian;
 * docs/protocol.md section 16). */
static int
counter_nonce(PyObject *counter, unsigned char nonce[NONCE_BYTES])
{
    unsigned long long value = PyLong_AsUnsignedLongLong(counter);
    if (value == (unsigned long long)-1 && PyErr_Occurred())
        return -1;
    memset(nonce, 0, 4);
    for (int i = 0; i < 8; i++)
        nonce[4 + i] = (unsigned char)(value >> (56 - 8 * i));
    return 0;
}

/* seal_counted(counter, head, body) -> head || ciphertext || tag: the associated data is head,
 * the nonce the counter's. */
static PyObject *
aead_seal_counted(Aead *self, PyObject *const *args, Py_ssize_t nargs)
{
    unsigned char nonce[NONCE_BYTES];
    Py_buffer head, body;
    if (check_call(self, nargs, "seal_counted(counter, head, body)") < 0
        || counter_nonce(args[0], nonce) < 0)
        return NULL;
    if (PyObject_GetBuffer(args[1], &head, PyBUF_SIMPLE) < 0)
        return NULL;
    if (PyObject_GetBuffer(args[2], &body, PyBUF_SIMPLE) < 0) {
        PyBuffer_Release(&head);
        return NULL;
    }
    PyObject *out = NULL;
    if (body.len > PY_SSIZE_T_MAX - TAG_BYTES - head.len) {
        PyErr_SetString(PyExc_OverflowError, "data too long to encrypt");
        goto done;
    }
    out = PyBytes_FromStringAndSize(NULL, head.len + body.len + TAG_BYTES);
    if (out == NULL)
        goto done;
    unsigned char *sealed = (unsigned char *)PyBytes_AS_STRING(out);
    memcpy(sealed, head.buf, (size_t)head.len);
    crypto_aead_chacha20poly1305_ietf_encrypt_detached(
        sealed + head.len, sealed + head.len + body.len, NULL, body.buf,
        (unsigned long long)body.len, head.buf, (unsigned long long)head.len, NULL, nonce,
        self->key);
done:
    PyBuffer_Release(&head);
    PyBuffer_Release(&body);
    return out;
}

/* open_counted(data, head_size, counter) -> the plaintext of data = head || ciphertext || tag,
 * head (its first head_size bytes) the associated data; InvalidTag if it does not verify. */
static PyObject *
aead_open_counted(Aead *self, PyObject *const *args, Py_ssize_t nargs)
{
    unsigned char nonce[NONCE_BYTES];
    Py_buffer data;
    if (check_call(self, nargs, "open_counted(data, head_size, counter)") < 0)
        return NULL;
    Py_ssize_t head_size = PyLong_AsSsize_t(args[1]);
    if (head_size == -1 && PyErr_Occurred())
        return NULL;
    if (head_size < 0) {
        PyErr_SetString(PyExc_ValueError, "head_size must not be negative");
        return NULL;
    }
    if (counter_nonce(args[2], nonce) < 0)
        return NULL;
    if (PyObject_GetBuffer(args[0], &data, PyBUF_SIMPLE) < 0)
        return NULL;
    PyObject *out = NULL;
    if (data.len - head_size < TAG_BYTES) {  /* no room for a tag after the head */
        PyErr_SetNone(invalid_tag);
        goto done;
    }
    const unsigned char *head = data.buf;
    const unsigned char *sealed = head + head_size;
    Py_ssize_t plain_len = data.len - head_size - TAG_BYTES;
    out = PyBytes_FromStringAndSize(NULL, plain_len);
    if (out == NULL)
        goto done;
    if (crypto_aead_chacha20poly1305_ietf_decrypt_detached(
            (unsigned char *)PyBytes_AS_STRING(out), NULL, sealed,
            (unsigned long long)plain_len, sealed + plain_len, head,
            (unsigned long long)head_size, nonce, self->key) != 0) {
        Py_CLEAR(out);
        PyErr_SetNone(invalid_tag);
    }
done:
    PyBuffer_Release(&data);
    return out;
}

static PyMethodDef aead_methods[] = {
    {"encrypt", (PyCFunction)(void (*)(void))aead_encrypt, METH_FASTCALL,
     "encrypt(nonce, data, associated_data) -> ciphertext + 16-byte tag"},
    {"decrypt", (PyCFunction)(void (*)(void))aead_decrypt, METH_FASTCALL,
     "decrypt(nonce, data, associated_data) -> plaintext; InvalidTag if it does not verify"},
    {"seal_counted", (PyCFunction)(void (*)(void))aead_seal_counted, METH_FASTCALL,
     "seal_counted(counter, head, body) -> head + ciphertext + tag (nonce from counter)"},
    {"open_counted", (PyCFunction)(void (*)(void))aead_open_counted, METH_FASTCALL,
     "open_counted(data, head_size, counter) -> plaintext of data[head_size:]"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject AeadType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "rlbridge.wire._chacha.ChaCha20Poly1305",
    .tp_doc = "ChaCha20-Poly1305 (RFC 8439) under one 32-byte key, from libsodium.",
    .tp_basicsize = sizeof(Aead),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)aead_init,
    .tp_dealloc = (destructor)aead_dealloc,
    .tp_methods = aead_methods,
};

static struct PyModuleDef chacha_module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "rlbridge.wire._chacha",
    .m_doc = "ChaCha20-Poly1305 from libsodium (see rlbridge.wire.aead).",
    .m_size = -1,
};

PyMODINIT_FUNC
PyInit__chacha(void)
{
    if (sodium_init() < 0) {
        PyErr_SetString(PyExc_ImportError, "libsodium failed to initialise");
        return NULL;
    }
    PyObject *exceptions = PyImport_ImportModule("cryptography.exceptions");
    if (exceptions == NULL)
        return NULL;
    invalid_tag = PyObject_GetAttrString(exceptions, "InvalidTag");
    Py_DECREF(exceptions);
    if (invalid_tag == NULL)
        return NULL;
    if (PyType_Ready(&AeadType) < 0)
        return NULL;
    PyObject *module = PyModule_Create(&chacha_module);
    if (module == NULL)
        return NULL;
    Py_INCREF(&AeadType);
    if (PyModule_AddObject(module, "ChaCha20Poly1305", (PyObject *)&AeadType) < 0
        || PyModule_AddStringConstant(module, "LIBSODIUM_VERSION",
                                      sodium_version_string()) < 0) {
        Py_DECREF(&AeadType);
        Py_DECREF(module);
        return NULL;
    }
    return module;
}
