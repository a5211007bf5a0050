/* cffi declarations of the C core (csrc/rtu.h, csrc/rtu_crc.h): the one place
 * the Python side learns the C API.  Read by pyrtu/core/_build_core.py. */

#define RTU_OK ...
#define RTU_EINVAL ...
#define RTU_EUNSUPPORTED ...
#define RTU_ENOSPC ...

#define RTU_CRC_BYTEWISE ...
#define RTU_CRC_SLICE8 ...
#define RTU_CRC_CLMUL ...
#define RTU_CRC_VCLMUL ...

#define RTU_TIMING_MODBUS ...
#define RTU_TIMING_WEG ...
#define RTU_RULE_NONE ...
#define RTU_RULE_FIXED ...
#define RTU_RULE_COUNT ...
#define RTU_RULE_MEI ...
#define RTU_DIR_REQUEST ...
#define RTU_DIR_RESPONSE ...
#define RTU_MAX_ADU_LIMIT ...

extern const uint8_t rtu_auchCRCHi[256];
extern const uint8_t rtu_auchCRCLo[256];
uint16_t rtu_crc16(const uint8_t *data, size_t len, uint16_t crc);
int rtu_crc16_path_available(int path);
int rtu_crc16_path(int path, const uint8_t *data, size_t len, uint16_t crc, uint16_t *out);
/* binding helper, defined in pyrtu/core/_build_core.py */
uint16_t rtu_crc16_bytes(const char *data, size_t len, uint16_t crc);

uint8_t rtu_lrc(const uint8_t *data, size_t len);

typedef struct {
    int64_t char_us;
    int64_t t15_us;
    int64_t t35_us;
} rtu_timing;
int rtu_timing_init(rtu_timing *t, uint32_t baudrate, unsigned bits_per_char, int rule);

typedef struct {
    uint8_t type;
    uint8_t off;
    uint8_t width;
    uint8_t mul;
    int16_t add;
} rtu_rule;
typedef struct { ...; } rtu_rules;

typedef struct {
    uint64_t offset;
    uint32_t length;
    uint8_t kind;
    uint8_t error;
    int64_t start_us;
    int64_t end_us;
    ...;
} rtu_event;

typedef struct {
    uint64_t pos;
    uint32_t flags;
    ...;
} rtu_mark;

typedef struct {
    int role;
    int strict;
    uint32_t max_adu;
    rtu_timing timing;
    int64_t flush_us;
    rtu_rules rules;
} rtu_config;

typedef struct {
    uint64_t frames[4];
    uint64_t discarded[6];
    uint64_t discard_events;
} rtu_counters;

int rtu_config_init(rtu_config *c, int role, uint32_t baudrate, unsigned bits_per_char, int rule);
int rtu_rules_set(rtu_rules *r, int direction, unsigned function, rtu_rule rule);
int rtu_predict(const rtu_rules *r, int direction, const uint8_t *adu, size_t n, size_t *length);

typedef struct {
    rtu_config cfg;
    rtu_counters counters;
    rtu_event event;
    ...;
} rtu_framer;

int rtu_framer_init(rtu_framer *f, const rtu_config *cfg);
void rtu_framer_reset(rtu_framer *f);
size_t rtu_framer_feed(rtu_framer *f, const uint8_t *data, size_t len, int64_t now_us);
void rtu_framer_handle_timer(rtu_framer *f, int64_t now_us);
int64_t rtu_framer_deadline(const rtu_framer *f);
int rtu_framer_poll(rtu_framer *f);
const uint8_t *rtu_framer_event_data(const rtu_framer *f);
void rtu_framer_sent(rtu_framer *f, const uint8_t *adu, size_t len);
size_t rtu_framer_needed(const rtu_framer *f);

typedef struct {
    rtu_counters counters;
    ...;
} rtu_parser;

int rtu_marks_from_chunks(const rtu_timing *t, const uint64_t *offsets, const int64_t *times,
                          size_t nchunks, uint64_t total, rtu_mark *out, size_t *nout);
int rtu_parser_init(rtu_parser *p, const rtu_config *cfg);
int rtu_parse(rtu_parser *p, const uint8_t *data, size_t len, const rtu_mark *marks, size_t nmarks,
              const uint64_t *offsets, const int64_t *times, size_t nchunks, rtu_event *out,
              size_t cap, size_t *nout);

/* ---- Modbus TCP: MBAP framing (csrc/rtu_mbap.c) ---- */
#define RTU_MBAP_HEADER_LEN ...
#define RTU_MBAP_MAX_LENGTH ...
#define RTU_MBAP_COMPLETE ...
#define RTU_MBAP_NEED ...
#define RTU_MBAP_INVALID ...
#define RTU_MBAP_NERR ...

typedef struct {
    uint64_t offset;
    uint64_t length;
    uint8_t kind;
    uint8_t error;
    ...;
} rtu_mbap_event;

typedef struct {
    uint64_t frames[4];
    uint64_t discarded[4];
    uint64_t discard_events;
} rtu_mbap_counters;

typedef struct {
    int error;
    rtu_mbap_counters counters;
    rtu_mbap_event event;
    ...;
} rtu_mbap_framer;

typedef struct {
    rtu_mbap_counters counters;
    ...;
} rtu_mbap_parser;

int rtu_mbap_inspect(const uint8_t *data, size_t n, size_t *length, int *error);
int rtu_mbap_encode(uint16_t transaction, uint8_t unit, const uint8_t *pdu, size_t pdu_len,
                    uint8_t *out, size_t cap, size_t *nout);
int rtu_mbap_framer_init(rtu_mbap_framer *f, int role);
size_t rtu_mbap_framer_feed(rtu_mbap_framer *f, const uint8_t *data, size_t len);
void rtu_mbap_framer_close(rtu_mbap_framer *f);
int rtu_mbap_framer_poll(rtu_mbap_framer *f);
const uint8_t *rtu_mbap_framer_event_data(const rtu_mbap_framer *f);
size_t rtu_mbap_framer_needed(const rtu_mbap_framer *f);
int rtu_mbap_parser_init(rtu_mbap_parser *p, int role);
int rtu_mbap_parse(rtu_mbap_parser *p, const uint8_t *data, size_t len, rtu_mbap_event *out,
                   size_t cap, size_t *nout);

/* ---- the image of a DataStore: plain reads answered in C (csrc/rtu_image.c) ---- */
#define RTU_IMAGE_COILS ...
#define RTU_IMAGE_DISCRETE_INPUTS ...
#define RTU_IMAGE_HOLDING_REGISTERS ...
#define RTU_IMAGE_INPUT_REGISTERS ...
#define RTU_IMAGE_TABLES ...
#define RTU_IMAGE_PLAIN ...
#define RTU_IMAGE_HELD ...
#define RTU_IMAGE_DEFER ...
#define RTU_IMAGE_MAX_ANSWER ...
typedef struct {
    uint32_t start;
    uint32_t count;
    uint32_t flags;
    uint16_t *values;
} rtu_image_range;
typedef struct {
    const rtu_image_range *ranges[4];
    uint32_t nranges[4];
} rtu_image;
int rtu_image_check(const rtu_image *img);
int rtu_image_answer(const rtu_image *img, const uint8_t *pdu, size_t len, uint8_t *out,
                     size_t cap, size_t *out_len);

/* ---- the virtual bus: sans-I/O schedule and I/O thread (csrc/rtu_vbus*.c) ---- */
#define RTU_VBUS_MAX_DROPS ...
#define RTU_VBUS_QUEUE ...
#define RTU_VBUS_OUT ...
#define RTU_VBUS_MAX_CHAR_NS ...
#define RTU_VBUS_MAX_LEAD_NS ...
#define RTU_VBUS_IO_STOPPED ...
#define RTU_VBUS_IO_WATCH ...
#define RTU_VBUS_IO_UNPLUG ...
#define RTU_VBUS_IO_ERRNO ...

typedef struct {
    uint64_t tx_bytes;
    uint64_t rx_bytes;
    uint64_t collided_bytes;
    uint64_t collisions;
    uint64_t overruns;
    uint64_t unheard;
    uint64_t batches;
} rtu_vbus_drop_counters;

typedef struct {
    int64_t q_time[...];
    uint8_t q_byte[...];
    uint32_t q_head;
    uint32_t q_len;
    int64_t tx_free;
    int64_t rx_end;
    int64_t last_start;
    uint8_t last_byte;
    uint8_t has_last;
    uint8_t alive;
    uint8_t cut;
    uint8_t echo;
    uint8_t due;
    int64_t unplug_left;
    int64_t event_at;
    int64_t batch_ns;
    uint32_t batch_bytes;
    uint32_t hold_len;
    int64_t hold_deadline;
    int64_t hold_end;
    uint32_t out_len;
    int64_t episode;
    rtu_vbus_drop_counters counters;
    uint8_t hold[...];
    uint8_t out[...];
    ...;
} rtu_vbus_drop;

typedef struct {
    uint32_t ndrops;
    int64_t char_ns;
    int64_t lead_ns;
    uint64_t wire_bytes;
    uint64_t collisions;
    uint64_t collided;
    int64_t coll_until;
    ...;
} rtu_vbus;

int rtu_vbus_init(rtu_vbus *s, rtu_vbus_drop *drops, uint32_t ndrops, int64_t char_ns,
                  int64_t lead_ns);
int rtu_vbus_plug(rtu_vbus *s, uint32_t drop);
int rtu_vbus_unplug(rtu_vbus *s, uint32_t drop);
int rtu_vbus_set_echo(rtu_vbus *s, uint32_t drop, int on);
int rtu_vbus_set_batch(rtu_vbus *s, uint32_t drop, int64_t batch_ns, uint32_t batch_bytes);
int rtu_vbus_set_unplug_after(rtu_vbus *s, uint32_t drop, int64_t left);
int rtu_vbus_cut(rtu_vbus *s, uint32_t drop, int64_t at);
int rtu_vbus_clear_hold(rtu_vbus *s, uint32_t drop);
size_t rtu_vbus_space(const rtu_vbus *s, uint32_t drop);
int rtu_vbus_transmit(rtu_vbus *s, uint32_t drop, const uint8_t *data, size_t len, int64_t now);
int64_t rtu_vbus_deadline(const rtu_vbus *s);
int rtu_vbus_service(rtu_vbus *s, int64_t now);
int rtu_vbus_take_due(rtu_vbus *s);
int rtu_vbus_written(rtu_vbus *s, uint32_t drop, size_t n, int heard);
int rtu_vbus_busy(const rtu_vbus *s);

/* ---- POSIX I/O (csrc/rtu_*_io.c): left out where there is none (_build_core.py) ---- */
typedef struct rtu_vbus_io rtu_vbus_io;
size_t rtu_vbus_io_size(void);
int rtu_vbus_io_init(rtu_vbus_io *io, rtu_vbus *s, int wake_fd, int watch_fd, int64_t anchor_ns);
void rtu_vbus_io_destroy(rtu_vbus_io *io);
void rtu_vbus_io_lock(rtu_vbus_io *io);
void rtu_vbus_io_unlock(rtu_vbus_io *io);
int rtu_vbus_io_set_fd(rtu_vbus_io *io, uint32_t drop, int fd, int heard);
int rtu_vbus_io_set_heard(rtu_vbus_io *io, uint32_t drop, int heard);
void rtu_vbus_io_stop(rtu_vbus_io *io);
int rtu_vbus_io_run(rtu_vbus_io *io);
int rtu_vbus_io_errno(const rtu_vbus_io *io);
int64_t rtu_vbus_io_now(void);
uint64_t rtu_vbus_io_wakeups(rtu_vbus_io *io);
/* ---- end of POSIX I/O ---- */

/* csrc/rtu_tcp.h: the answers at the head of a Modbus TCP client's receive buffer */
typedef struct {
    size_t used;
    size_t ans_off;
    size_t ans_len;
    uint32_t late;
    uint32_t late_after;
    int error;
} rtu_tcp_scan_result;
int rtu_tcp_scan(const uint8_t *buf, size_t n, unsigned tid, rtu_tcp_scan_result *s);

/* ---- POSIX I/O (csrc/rtu_*_io.c): left out where there is none (_build_core.py) ---- */
/* csrc/rtu_xfer.h: one master xfer on a serial descriptor */
#define RTU_XFER_ANSWER 0
#define RTU_XFER_STALE 1
#define RTU_XFER_SHORT 2
#define RTU_XFER_ERRNO 3
#define RTU_XFER_GONE 4
#define RTU_XFER_CANCELLED 5
#define RTU_XFER_SPIN_MAX 1000000
#define RTU_XFER_STAGE_WRITE 1
#define RTU_XFER_STAGE_READ 2
typedef struct {
    int fd;
    int drain;
    int look;
    int cancel_fd;
    const uint8_t *req;
    size_t req_len;
    int64_t send_at;
    int64_t spin_ns;
    int64_t first_wake;
    int64_t timeout_ns;
    int64_t char_ns;
    size_t expect;
    size_t short_len;
    uint8_t *buf;
    size_t cap;
    int status;
    int sent;
    int err;
    int stage;
    int64_t start;
    int64_t end;
    size_t first_n;
    int64_t first_t;
    size_t n;
    int64_t last_t;
    uint32_t reads;
} rtu_xfer;
int rtu_xfer_io_run(rtu_xfer *x);
#define RTU_EBUSY -4
typedef struct rtu_xfer_worker rtu_xfer_worker;
size_t rtu_xfer_worker_size(void);
int rtu_xfer_worker_start(rtu_xfer_worker *w, rtu_xfer *x, int notify_fd);
int rtu_xfer_worker_submit(rtu_xfer_worker *w);
int rtu_xfer_worker_rc(rtu_xfer_worker *w);
void rtu_xfer_worker_stop(rtu_xfer_worker *w);
/* ---- end of POSIX I/O ---- */

/* ---- POSIX I/O (csrc/rtu_*_io.c): left out where there is none (_build_core.py) ---- */
/* csrc/rtu_tcp.h: one Modbus TCP client transaction (csrc/rtu_tcp_io.c) */
#define RTU_TCP_ANSWER 0
#define RTU_TCP_EXCEPTION 1
#define RTU_TCP_MISMATCH 2
#define RTU_TCP_TIMEOUT 3
#define RTU_TCP_CLOSED 4
#define RTU_TCP_ERRNO 5
#define RTU_TCP_BAD_HEADER 6
#define RTU_TCP_INTERRUPTED 7
#define RTU_TCP_NOTE 16
#define RTU_TCP_STAGE_SEND 1
#define RTU_TCP_STAGE_RECEIVE 2
#define RTU_TCP_REQ_CAP 260
#define RTU_TCP_MIN_CAP 520
typedef struct rtu_tcp_io rtu_tcp_io;
typedef struct {
    int fd;
    int send;
    int awaited;
    unsigned tid;
    unsigned unit;
    const uint8_t *pdu;
    size_t pdu_len;
    int64_t timeout_ns;
    uint8_t *buf;
    size_t cap;
    uint8_t req[260];
    int status;
    int err;
    int stage;
    int64_t start;
    int64_t deadline;
    int64_t end;
    size_t n;
    rtu_tcp_scan_result scan;
    uint8_t answer[253];
    rtu_tcp_io *io;
} rtu_tcp_xfer;
int rtu_tcp_xfer_run(rtu_tcp_xfer *x);
int rtu_tcp_xfer_call(rtu_tcp_xfer *x, unsigned tid, unsigned unit, const char *pdu,
                      size_t pdu_len, int awaited, int64_t timeout_ns);
int rtu_tcp_xfer_word(rtu_tcp_xfer *x);
/* ---- end of POSIX I/O ---- */

/* ---- POSIX I/O (csrc/rtu_*_io.c): left out where there is none (_build_core.py) ---- */
/* csrc/rtu_mux.h: many Modbus TCP client connections on one I/O thread */
typedef struct {
    uint64_t token;
    uint32_t conn;
    int32_t status;
    int32_t err;
    int32_t stage;
    uint32_t late;
    uint32_t tid;
    int64_t start;
    int64_t end;
    uint32_t flags;
    uint32_t len;
    uint8_t adu[254];
} rtu_mux_done;
#define RTU_MUX_REPEATING 1
#define RTU_MUX_RESENT 2
typedef struct rtu_mux rtu_mux;
size_t rtu_mux_size(uint32_t nconns);
int rtu_mux_init(rtu_mux *m, uint32_t nconns);
void rtu_mux_destroy(rtu_mux *m);
int rtu_mux_fd(const rtu_mux *m);
int rtu_mux_attach(rtu_mux *m, uint32_t conn, int fd);
int rtu_mux_detach(rtu_mux *m, uint32_t conn);
int rtu_mux_submit(rtu_mux *m, uint32_t conn, uint64_t token, unsigned tid, unsigned unit,
                   const char *pdu, size_t pdu_len, int awaited, int64_t timeout_ns);
int rtu_mux_repeat(rtu_mux *m, uint32_t conn, int64_t first_ns, int64_t interval_ns);
int rtu_mux_unrepeat(rtu_mux *m, uint32_t conn);
int rtu_mux_service(rtu_mux *m);
int64_t rtu_mux_deadline(const rtu_mux *m);
size_t rtu_mux_take(rtu_mux *m, rtu_mux_done *out, size_t cap);
int rtu_mux_errno(const rtu_mux *m);
uint64_t rtu_mux_services(const rtu_mux *m);
/* ---- end of POSIX I/O ---- */

/* ---- POSIX I/O (csrc/rtu_*_io.c): left out where there is none (_build_core.py) ---- */
/* csrc/rtu_serve.h: the server engine, a thread serving a Modbus TCP server's clients */
#define RTU_SERVE_IN_CAP ...
#define RTU_SERVE_OUT_CAP ...
#define RTU_SERVE_REQUEST ...
#define RTU_SERVE_CLOSED ...
#define RTU_SERVE_BAD_HEADER ...
#define RTU_SERVE_STALLED ...
typedef struct rtu_serve rtu_serve;
typedef struct {
    uint32_t conn;
    int32_t kind;
    int32_t err;
    uint32_t len;
    int64_t at;
    uint8_t adu[260];
} rtu_serve_event;
typedef struct {
    int64_t connected;
    int64_t last_request;
    int64_t partial_since;
    uint64_t answered;
    uint64_t by_function[5];
    uint32_t unsent;
    uint32_t handed;
} rtu_serve_conn_state;
typedef struct {
    uint64_t requests;
    uint64_t answered;
    uint64_t handed;
    uint64_t by_function[5];
} rtu_serve_stats;
size_t rtu_serve_size(uint32_t capacity);
int rtu_serve_init(rtu_serve *s, uint32_t capacity, uint32_t max_unsent);
void rtu_serve_destroy(rtu_serve *s);
int rtu_serve_errno(const rtu_serve *s);
int rtu_serve_fd(const rtu_serve *s);
void rtu_images_lock(void);
void rtu_images_unlock(void);
int rtu_serve_attach(rtu_serve *s, uint32_t conn, int fd, const rtu_image *const *routes,
                     int defer);
int rtu_serve_defer(rtu_serve *s, uint32_t conn, int on);
int rtu_serve_detach(rtu_serve *s, uint32_t conn);
int rtu_serve_send(rtu_serve *s, uint32_t conn, const uint8_t *adu, size_t len);
size_t rtu_serve_take(rtu_serve *s, rtu_serve_event *out, size_t cap);
int rtu_serve_conn(rtu_serve *s, uint32_t conn, rtu_serve_conn_state *st);
int rtu_serve_stats_get(rtu_serve *s, rtu_serve_stats *out);
/* ---- end of POSIX I/O ---- */

/* ---- TLS (csrc/rtu_tls_io.c, over OpenSSL): left out where OpenSSL is not found ---- */
/* csrc/rtu_tls.h: the TLS of an mbaps:// client */
typedef struct rtu_tls_ctx rtu_tls_ctx;
typedef struct rtu_tls_conn rtu_tls_conn;
typedef struct rtu_tls_session rtu_tls_session;
#define RTU_TLS_DONE 0
#define RTU_TLS_TIMEOUT 1
#define RTU_TLS_VERIFY 2
#define RTU_TLS_FAILED 3
#define RTU_TLS_CLOSED 4
#define RTU_TLS_ERRNO 5
#define RTU_TLS_INTERRUPTED 6
#define RTU_TLS_V1_2 0x0303
#define RTU_TLS_V1_3 0x0304
int rtu_tls_ctx_new(rtu_tls_ctx **out, const char *cert, const char *key, const char *ca,
                    int min_version, int max_version, char *err, size_t errlen);
void rtu_tls_ctx_free(rtu_tls_ctx *ctx);
int rtu_tls_conn_new(rtu_tls_conn **out, rtu_tls_ctx *ctx, int fd, const char *host,
                     rtu_tls_session *session);
void rtu_tls_conn_free(rtu_tls_conn *c);
void rtu_tls_close_notify(rtu_tls_conn *c);
int rtu_tls_handshake(rtu_tls_conn *c, int64_t timeout_ns);
const char *rtu_tls_conn_message(rtu_tls_conn *c);
int rtu_tls_conn_errno(rtu_tls_conn *c);
int rtu_tls_conn_reused(rtu_tls_conn *c);
int rtu_tls_conn_version(rtu_tls_conn *c);
rtu_tcp_io *rtu_tls_conn_io(rtu_tls_conn *c);
rtu_tls_session *rtu_tls_conn_session(rtu_tls_conn *c);
void rtu_tls_session_free(rtu_tls_session *s);
/* ---- end of TLS ---- */
